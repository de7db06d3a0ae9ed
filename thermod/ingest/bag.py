"""A ROS recording (MCAP, rosbag2 directory, ROS 1 .bag) → format v1 (`import_bag`).

Frames come from one sensor_msgs/Image topic (raw counts: mono16/16UC1, or 8-bit widened to
uint16; other encodings and CompressedImage are refused by name), gyro samples from one
sensor_msgs/Imu topic (``angular_velocity``, taken as raw gyro-frame rates), both stamped with their
header stamps, or with the bag's log times for a topic whose driver leaves them 0 (`_Clock`).
Topics are autodetected when the bag has one of each (or one of the usual names). The calibration,
in order of precedence: a TOML file's [calibration] keys, the ``thermod`` metadata of an MCAP
written by thermod, a sensor_msgs/CameraInfo topic plus τ (the detector time constant, which no ROS
message carries); what CameraInfo cannot give (K all zeros, another size) the TOML must. Format v1
holds one calibration: when the ``thermod`` records of a recording hold several (the daemon's
changed while it recorded), the last one written is imported for every frame, with a warning.
Messages are streamed into the output (`thermod.io.stream_recording.RecordWriter`), never held.
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
COMPRESSED = "sensor_msgs/msg/CompressedImage"
COMPRESSED_NOTE = (" (PNG or JPEG frames, which thermod does not decode: record the driver's raw "
                   "sensor_msgs/Image topic)")


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
            info, shape, frame_t, gyro_t, clocks = _stream(bag, writer, image_topic, imu_topic, info_topic)
            calib = _calibration(bag, base, info, info_topic, image_topic, shape, frame_t, gyro_t,
                                 calibration, tau_s)
            writer.finish(calib, {"imported_from": str(bag.path), "image_topic": image_topic,
                                  "imu_topic": imu_topic, "imported_calibration": source,
                                  "image_clock": clocks[image_topic], "imu_clock": clocks[imu_topic]})
        except BaseException:
            writer.discard()
            raise
    return BagImport(out, writer.written["frames"], writer.written["gyro"], image_topic, imu_topic, source)


def pick_topic(
    bag: mcap.Bag, msgtype: str, wanted: str | None, usual: tuple, what: str, required: bool = True
) -> str | None:
    """The topic of `msgtype` to read: `wanted`, else the only one, else one of the `usual` names."""
    have = sorted(t for t, m in bag.topics.items() if m == msgtype)
    if wanted is not None:
        if wanted not in bag.topics:
            raise RecordingError(bag.path, wanted, f"no such topic; {msgtype} topics: {have or 'none'}")
        if bag.topics[wanted] != msgtype:
            raise RecordingError(bag.path, wanted, f"is {bag.topics[wanted]}, expected {msgtype}"
                                 + (COMPRESSED_NOTE if bag.topics[wanted] == COMPRESSED else ""))
        return wanted
    if len(have) == 1:
        return have[0]
    for name in usual:
        if name in have:
            return name
    if not have:
        if not required:
            return None
        packed = sorted(t for t, m in bag.topics.items() if m == COMPRESSED and msgtype == mcap.IMAGE)
        raise RecordingError(bag.path, what, f"no {msgtype} topic (topics: {sorted(bag.topics) or 'none'})"
                             + (f"; {', '.join(packed)}: {COMPRESSED}{COMPRESSED_NOTE}" if packed else ""))
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


def _encoding_problem(enc: str) -> str:
    """Why frames of encoding `enc` are not imported."""
    low = enc.lower()
    kind = ("float values (a temperature image or a processed view), not raw detector counts"
            if low.startswith(("32f", "64f")) else
            "a Bayer colour mosaic" if low.startswith("bayer") else
            "a YUV colour image" if low.startswith(("yuv", "uyvy", "yuyv", "nv")) else
            "a colour image (a colourised view?)" if low.startswith(("rgb", "bgr")) else
            "not a single-channel image encoding thermod reads")
    return (f"image encoding {enc!r}: {kind}; {', '.join(mcap.RAW_ENCODINGS)} expected (choose the raw "
            "image topic with --image-topic)")


class _Clock:
    """The times of one topic's messages: their header stamps or, when its first message is not
    stamped (0, as some drivers leave it), the bag's log times (when the recorder received each)
    for the whole topic, with a warning. Counts stamps that are 0 among stamped ones, or not after
    the one before, for `report`."""

    def __init__(self, path, topic: str):
        self.path, self.topic = path, topic
        self.source: str | None = None
        self.unstamped = self.backwards = 0
        self.first_back: tuple[int, float, float] | None = None
        self._n, self._last = 0, -np.inf

    def __call__(self, msg, log_ns: int) -> float | None:
        s = msg.header.stamp
        zero = int(s.sec) == 0 and int(s.nanosec) == 0
        if self.source is None:
            self.source = "log time" if zero else "header stamp"
            if zero:
                log.warning("%s: %s: header stamp 0 (the driver does not stamp its messages): the bag's "
                            "log times are taken instead, i.e. when the recorder received each message, "
                            "transport latency included", self.path, self.topic)
        self._n += 1
        if self.source == "log time":
            t = int(log_ns) * 1e-9
        elif zero:
            self.unstamped += 1
            return None
        else:
            t = mcap.from_stamp(s)
        if t <= self._last:
            self.backwards += 1
            if self.first_back is None:
                self.first_back = (self._n, t, self._last)
        self._last = max(self._last, t)
        return t

    def report(self) -> None:
        if self.unstamped:
            log.warning("%s: %s: %d messages with header stamp 0 among stamped ones dropped",
                        self.path, self.topic, self.unstamped)
        if self.backwards:
            i, t, last = self.first_back
            log.warning("%s: %s: %d %s not after the one before (the first: message %d at %.6f s, after "
                        "%.6f s): put in time order, repeated times dropped", self.path, self.topic,
                        self.backwards, self.source + "s", i, t, last)


def _stream(bag, writer, image_topic, imu_topic, info_topic):
    """Messages → writer; returns the first CameraInfo's intrinsics, the frames' shape, the frame and
    gyro times, and the clock each of the two topics was read on (`_Clock`)."""
    info, frame_t, gyro_t = None, [], []
    batch = np.zeros(GYRO_BATCH, GYRO_DTYPE)
    n = 0
    clocks = {image_topic: _Clock(bag.path, image_topic), imu_topic: _Clock(bag.path, imu_topic)}
    encoding = shape = dtype = None
    n_images = usable = 0
    topics = [t for t in (image_topic, imu_topic, info_topic) if t is not None]

    def flush():
        nonlocal n, usable
        chunk = batch[:n].copy()
        writer.add("gyro", {"sample_seq": len(gyro_t)}, chunk)
        gyro_t.extend(chunk["t"].tolist())
        usable += int(np.isfinite(chunk["rate"]).all(axis=1).sum())
        n = 0

    for topic, msg, log_ns in bag.messages(topics):
        with _fields(bag, topic):
            if topic == image_topic:
                enc = str(msg.encoding)
                if enc not in mcap.RAW_ENCODINGS:
                    raise RecordingError(bag.path, topic, _encoding_problem(enc))
                image = mcap.image_array(msg, bag.path, topic)
                t = clocks[topic](msg, log_ns)
            elif topic == imu_topic:
                t = clocks[topic](msg, log_ns)
                v = msg.angular_velocity
                sample = (t, (float(v.x), float(v.y), float(v.z)))
            elif info is None:
                info = mcap.camera_info_intrinsics(msg)
        if topic == image_topic:
            if encoding is None:
                encoding, shape, dtype = enc, image.shape, image.dtype
            elif image.dtype != dtype or image.shape != shape:
                raise RecordingError(bag.path, topic, f"frames change from {shape[1]}×{shape[0]} {encoding} "
                                     f"to {image.shape[1]}×{image.shape[0]} {enc} (message {n_images + 1}): "
                                     "one size and depth expected")
            n_images += 1
            if t is None:
                continue
            writer.add("raw", {"t": t, "frame_id": len(frame_t)}, image.astype(np.uint16, copy=False))
            frame_t.append(t)
        elif topic == imu_topic:
            if t is None:
                continue
            with np.errstate(over="ignore"):    # a rate beyond float32: inf, dropped as non-finite
                batch[n] = sample
            n += 1
            if n == GYRO_BATCH:
                flush()
    if n:
        flush()
    for clock in clocks.values():
        clock.report()
    if not frame_t:
        raise RecordingError(bag.path, image_topic, "no frames")
    if gyro_t and not usable:        # a recording whose gyro is all dropped would deblur nothing
        raise RecordingError(bag.path, imu_topic, f"none of its {len(gyro_t)} messages has a finite "
                             "angular_velocity")
    return info, shape, frame_t, gyro_t, {t: c.source or "no message" for t, c in clocks.items()}


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


def _calibration(bag, base, info, info_topic, image_topic, shape, frame_t, gyro_t, calibration,
                 tau) -> Calibration:
    """The recording's calibration: `base` (thermod metadata), else the CameraInfo `info` and the
    bag's rates, then the TOML file `calibration` over it. Without a usable CameraInfo the TOML must
    give fx and fy, and τ must come from --tau or the TOML: defaults would pass for the camera's."""
    h, w = shape
    if base is None:
        rates = (("frame_rate_hz", _median_rate(frame_t)), ("rate_hz", _median_rate(gyro_t)))
        extra = {k: r for k, r in rates if r is not None}
        if tau is not None:
            extra["tau_s"] = tau
        problem = (f"no {mcap.CAMERA_INFO} {'message' if info_topic else 'topic'} to take the camera "
                   "intrinsics from" if info is None else _info_problem(info, shape))
        if problem is None:
            try:
                kw = {k: info[k] for k in ("width", "height", "fx", "fy", "cx", "cy")}
                base = Calibration(**kw, **extra)
            except (TypeError, ValueError) as e:
                problem = f"unusable camera model ({e})"
        lacking = _toml_lacks(calibration, ("fx", "fy") if problem else ()) + (
            _toml_lacks(calibration, ("tau_s",)) if tau is None else [])
        where = info_topic or "CameraInfo"
        if lacking:
            need = (f"{problem}; " if problem else "") + f"{calibration} gives no {' nor '.join(lacking)}"
            raise RecordingError(bag.path, where, f"{need}: add them to its [calibration] table"
                                 + (" (τ: or give --tau)" if "tau_s" in lacking else ""))
        if problem is not None and calibration is None:
            raise RecordingError(bag.path, where, f"{problem}: give --calibration model.toml with fx, fy "
                                 "(and cx, cy) in its [calibration] table")
        if problem is not None:
            if info_topic is not None:
                log.warning("%s: %s: %s: the intrinsics of %s are taken", bag.path, info_topic, problem,
                            calibration)
            # fx, fy are the TOML's; the frames give the size, the centre the default principal point
            base = Calibration(width=w, height=h, fx=float(w), fy=float(w), cx=(w - 1) / 2, cy=(h - 1) / 2,
                               **extra)
        elif info["distorted"]:
            log.warning("%s: %s declares lens distortion (%s); thermod models a pinhole camera and ignores "
                        "it", bag.path, where, info["distortion_model"] or "no model named")
        log.warning(
            "gyro axes taken as the camera axes (R_cam_gyro = I), bias 0, time offset 0: give "
            "--calibration to set them"
        )
    if calibration is not None:
        from thermod.io import calibration_file

        base = calibration_file.load_calibration(calibration, base)
    if (base.height, base.width) != (h, w):
        raise RecordingError(bag.path, image_topic, f"frames are {w}×{h}, the calibration "
                             f"({calibration or 'thermod metadata'}) is for {base.width}×{base.height}")
    return base


def _info_problem(info: dict, shape: tuple[int, int]) -> str | None:
    """Why a CameraInfo's intrinsics cannot be the camera's, or None."""
    k = np.array([info[n] for n in ("fx", "fy", "cx", "cy")])
    if not np.all(np.isfinite(k)) or not np.any(k):
        return ("K is all zeros (what an uncalibrated camera driver publishes)" if not np.any(k) else
                f"K holds non-finite values (fx, fy, cx, cy = {', '.join(map(str, k))})")
    if (info["height"], info["width"]) != tuple(shape):
        return (f"CameraInfo is for {info['width']}×{info['height']} images, the frames are "
                f"{shape[1]}×{shape[0]}")
    return None


def _toml_lacks(calibration, keys: tuple) -> list[str]:
    """The `keys` the [calibration] table of the TOML file `calibration` does not give."""
    if calibration is None or not keys:
        return []
    from thermod.io.toml_tables import read_toml

    table = read_toml(Path(calibration)).get("calibration")
    return [k for k in keys if not isinstance(table, dict) or k not in table]
