"""A ROS recording (MCAP, rosbag2 directory, ROS 1 .bag) → format v1 (`import_bag`).

Frames come from one sensor_msgs/Image topic (raw counts: mono16/16UC1, or 8-bit widened to
uint16), gyro samples from one sensor_msgs/Imu topic (``angular_velocity``, taken as raw gyro-frame
rates), both stamped with their header stamps. Topics are autodetected when the bag has one of each
(or one of the usual names). The calibration, in order of precedence: a TOML file's [calibration]
keys, the ``thermod`` metadata of an MCAP written by thermod, a sensor_msgs/CameraInfo topic plus τ
(the detector time constant, which no ROS message carries). Format v1 holds one calibration: when
the ``thermod`` records of a recording hold several (the daemon's changed while it recorded), the
last one written is imported for every frame, with a warning. Messages are streamed into the output
(`thermod.io.stream_recording.RecordWriter`), never held.
"""

from __future__ import annotations

import contextlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thermod.errors import RecordingError, ThermodError
from thermod.io import mcap
from thermod.io.stream_recording import RecordWriter
from thermod.io.wire import GYRO_DTYPE
from thermod.paths import output_problem
from thermod.physics.calibration import Calibration

log = logging.getLogger(__name__)

IMAGE_TOPICS = (mcap.RAW_TOPIC, "/flir_boson/image_raw", "/thermal/image", "/camera/image_raw", "/image_raw")
IMU_TOPICS = (mcap.IMU_TOPIC, "/imu", "/imu/data_raw", "/mavros/imu/data_raw", "/mavros/imu/data")
GYRO_BATCH = 1024


@dataclass(frozen=True)
class BagImport:
    """What `import_bag` wrote."""

    path: Path
    frames: int
    gyro_samples: int
    image_topic: str
    imu_topic: str
    calibration_source: str


def import_bag(input_path, output, *, image_topic: str | None = None, imu_topic: str | None = None,
               camera_info_topic: str | None = None, calibration=None,
               tau_s: float | None = None) -> BagImport:
    """Stream a bag's frames and gyro into the recording `output` (module docstring); on any failure
    nothing is left at `output`. `calibration`: a TOML file whose [calibration] keys override the bag's."""
    out = Path(output)
    if (problem := output_problem(out)) is not None:     # before reading the bag
        raise RecordingError(out, "file", problem)
    with mcap.Bag(input_path) as bag:
        image_topic = pick_topic(bag, mcap.IMAGE, image_topic, IMAGE_TOPICS, "image-topic")
        imu_topic = pick_topic(bag, mcap.IMU, imu_topic, IMU_TOPICS, "imu-topic")
        beside = image_topic.rsplit("/", 1)[0] + "/camera_info"
        info_topic = pick_topic(bag, mcap.CAMERA_INFO, camera_info_topic, (beside, mcap.CAMERA_INFO_TOPIC),
                                "camera-info-topic", required=False)
        base, source = _base_calibration(bag, info_topic, calibration, tau_s)
        writer = RecordWriter(out)
        try:
            info, frame_t, gyro_t = _stream(bag, writer, image_topic, imu_topic, info_topic)
            calib = _calibration(bag, base, info, frame_t, gyro_t, calibration, tau_s)
            _check_size(bag, image_topic, writer.frame_shape, calib, calibration, source)
            writer.finish(calib, {"imported_from": str(bag.path), "image_topic": image_topic,
                                  "imu_topic": imu_topic, "imported_calibration": source})
        except BaseException:
            writer.discard()
            raise
    return BagImport(out, writer.written["frames"], writer.written["gyro"], image_topic, imu_topic, source)


def _check_size(bag, topic: str, shape, calib: Calibration, calibration, source: str) -> None:
    """The frames are the calibration's width × height, else an error naming the bag, the topic and
    where the calibration came from (before `finish`, which would name the output)."""
    if shape is not None and tuple(shape) != (calib.height, calib.width):
        where = f"--calibration {calibration}" if calibration is not None else source
        raise RecordingError(bag.path, topic, f"frames are {shape[1]}×{shape[0]} (width×height) but the "
                             f"calibration ({where}) is {calib.width}×{calib.height}")


def pick_topic(
    bag: mcap.Bag, msgtype: str, wanted: str | None, usual: tuple, what: str, required: bool = True
) -> str | None:
    """The topic of `msgtype` to read: `wanted`, else the only one, else one of the `usual` names."""
    have = sorted(t for t, m in bag.topics.items() if m == msgtype)
    if wanted is not None:
        if wanted not in bag.topics:
            raise RecordingError(bag.path, wanted, f"no such topic; {msgtype} topics: {have or 'none'}")
        if bag.topics[wanted] != msgtype:
            raise RecordingError(bag.path, wanted, f"is {bag.topics[wanted]}, expected {msgtype}")
        return wanted
    if len(have) == 1:
        return have[0]
    for name in usual:
        if name in have:
            return name
    if not have:
        if not required:
            return None
        raise RecordingError(bag.path, what, f"no {msgtype} topic (topics: {sorted(bag.topics) or 'none'})")
    raise RecordingError(bag.path, what, f"several {msgtype} topics {have}: choose one with --{what}")


def _base_calibration(bag: mcap.Bag, info_topic: str | None, calibration,
                      tau) -> tuple[Calibration | None, str]:
    """What the bag says about the calibration before reading messages (thermod metadata), or None
    when it must come from CameraInfo; checks up front that nothing required is missing."""
    meta = bag.metadata.get(mcap.METADATA_NAME, {})
    if "calibration" in meta:
        try:
            d = json.loads(meta["calibration"])
            if not isinstance(d, dict):
                raise TypeError(f"expected a JSON object of calibration keys, got {type(d).__name__}")
            base = Calibration.from_dict(d)
        except (ValueError, TypeError, KeyError, OverflowError, RecursionError) as e:
            raise RecordingError(bag.path, "metadata thermod.calibration", f"unusable ({e})") from None
        _warn_if_changed(bag)
        return base, "thermod metadata"
    if calibration is not None:
        return None, "calibration file"
    missing = []
    if info_topic is None:
        missing.append("camera intrinsics (no sensor_msgs/msg/CameraInfo topic)")
    elif bag.truncated and not bag.counts.get(info_topic):    # a cut file's counts are exact
        missing.append(f"camera intrinsics (no complete message on {info_topic})")
    if tau is None:
        missing.append("the detector time constant (--tau S)")
    if missing:
        cut = (" (a truncated recording has none when its recorder was stopped before it received the "
               "daemon's calibration, or was one that wrote it at the end)") if bag.truncated else ""
        raise ThermodError(
            f"{bag.path}: no thermod calibration in the bag; missing {' and '.join(missing)}{cut}: "
            "give --calibration model.toml (a [calibration] table) or those"
        )
    return None, "camera_info"


def _warn_if_changed(bag: mcap.Bag) -> None:
    """Say so when the ``thermod`` records hold more than one calibration: every frame is imported with
    the last one, whatever was in force when it was taken."""
    changes, last = [], None
    for name, record in bag.metadata_records:
        if name == mcap.METADATA_NAME and "calibration" in record:
            try:
                c = json.dumps(json.loads(record["calibration"]), sort_keys=True)
            except (ValueError, TypeError, RecursionError):
                continue            # an earlier record left unreadable: the last one is what is imported
            if c != last:
                changes.append(record.get("from_t"))
                last = c
    if len(changes) > 1:
        since = f" (in force from t = {changes[-1]} s)" if changes[-1] is not None else ""
        log.warning("%s: the calibration changed while recording (%d calibrations in the %s metadata); "
                    "format v1 holds one, so every frame is imported with the last one written%s",
                    bag.path, len(changes), mcap.METADATA_NAME, since)


def _median_rate(t: list[float] | np.ndarray) -> float | None:
    dt = np.diff(np.asarray(t, np.float64))
    dt = dt[dt > 0]
    return float(1.0 / np.median(dt)) if len(dt) else None


def _stream(bag, writer, image_topic, imu_topic, info_topic):
    """Messages → writer; returns the first CameraInfo's intrinsics and the frame and gyro times."""
    info, frame_t, gyro_t = None, [], []
    batch = np.zeros(GYRO_BATCH, GYRO_DTYPE)
    n = 0
    topics = [t for t in (image_topic, imu_topic, info_topic) if t is not None]
    for topic, msg in bag.messages(topics):
        with _fields(bag, topic):
            if topic == image_topic:
                image = mcap.image_array(msg, bag.path, topic)
                t = mcap.from_stamp(msg.header.stamp)
            elif topic == imu_topic:
                v = msg.angular_velocity
                sample = (mcap.from_stamp(msg.header.stamp), (float(v.x), float(v.y), float(v.z)))
            elif info is None:
                info = mcap.camera_info_intrinsics(msg)
        if topic == image_topic:
            if image.dtype == np.float32:
                raise RecordingError(
                    bag.path,
                    topic,
                    "32FC1 frames are not raw detector counts; choose the raw image topic with --image-topic",
                )
            writer.add("raw", {"t": t, "frame_id": len(frame_t)}, image.astype(np.uint16, copy=False))
            frame_t.append(t)
        elif topic == imu_topic:
            with np.errstate(over="ignore"):    # a rate beyond float32: inf, dropped as non-finite
                batch[n] = sample
            n += 1
            if n == GYRO_BATCH:
                writer.add("gyro", {"sample_seq": len(gyro_t)}, batch[:n].copy())
                gyro_t.extend(batch["t"][:n].tolist())
                n = 0
    if n:
        writer.add("gyro", {"sample_seq": len(gyro_t)}, batch[:n].copy())
        gyro_t.extend(batch["t"][:n].tolist())
    if not frame_t:
        raise RecordingError(bag.path, image_topic, "no frames")
    if sum(writer.dropped.values()):
        raise RecordingError(bag.path, image_topic, f"frames of varying size ({dict(writer.dropped)})")
    return info, frame_t, gyro_t


@contextlib.contextmanager
def _fields(bag, topic: str):
    """A message without the fields of the type its schema names (a schema that does not match its
    messages decodes into another type): a RecordingError naming the bag and the topic."""
    try:
        yield
    except (AttributeError, TypeError, IndexError, ValueError, OverflowError) as e:
        raise RecordingError(bag.path, topic, f"a message without the fields of {bag.topics.get(topic)} "
                             f"({type(e).__name__}: {e}): its schema does not match the type it "
                             "names") from None


def _calibration(bag, base, info, frame_t, gyro_t, calibration, tau) -> Calibration:
    if base is None and info is None and calibration is None:
        # a CameraInfo topic without a message: defaults would pass for the camera's model
        raise RecordingError(bag.path, "CameraInfo", "no message to take the camera intrinsics from; "
                             "give --calibration model.toml (a [calibration] table)")
    if base is None and info is not None:
        if info["distorted"]:
            log.warning(
                "%s: CameraInfo declares lens distortion; thermod models a pinhole camera and ignores it",
                bag.path,
            )
        kw = {k: info[k] for k in ("width", "height", "fx", "fy", "cx", "cy")}
        if tau is not None:
            kw["tau_s"] = tau
        for key, rate in (("frame_rate_hz", _median_rate(frame_t)), ("rate_hz", _median_rate(gyro_t))):
            if rate is not None:
                kw[key] = rate
        try:
            base = Calibration(**kw)
        except (TypeError, ValueError) as e:
            raise RecordingError(bag.path, "CameraInfo", f"unusable camera model ({e})") from None
        log.warning(
            "gyro axes taken as the camera axes (R_cam_gyro = I), bias 0, time offset 0: give "
            "--calibration to set them"
        )
    if calibration is not None:
        from thermod.io import calibration_file

        return calibration_file.load_calibration(calibration, base)
    return base
