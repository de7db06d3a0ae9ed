"""`thermod import IN -o OUT.h5`: a ROS recording (MCAP, rosbag2 directory, ROS 1 .bag) → format v1;
with ``--gyro LOG``, IN is a thermal video synced to a flight-controller log (`thermod.cli.import_flight`);
a video without ``--gyro`` gets a gyro estimated from its pictures (`thermod.cli.import_video`).

Frames come from one sensor_msgs/Image topic (raw counts: mono16/16UC1, or 8-bit widened to
uint16), gyro samples from one sensor_msgs/Imu topic (``angular_velocity``, taken as raw gyro-frame
rates), both stamped with their header stamps. Topics are autodetected when the bag has one of
each (or one of the usual names). The calibration, in order of precedence: ``--calibration
model.toml`` (its [calibration] keys), the ``thermod`` metadata of an MCAP written by thermod, a
sensor_msgs/CameraInfo topic plus ``--tau`` (the detector time constant, which no ROS message
carries). Messages are streamed into the output (`thermod.cli.record.RecordWriter`), never held.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from thermod.errors import RecordingError, ThermodError
from thermod.io import mcap
from thermod.io.wire import GYRO_DTYPE
from thermod.physics.calibration import Calibration

log = logging.getLogger(__name__)

IMAGE_TOPICS = (mcap.RAW_TOPIC, "/flir_boson/image_raw", "/thermal/image", "/camera/image_raw", "/image_raw")
IMU_TOPICS = (mcap.IMU_TOPIC, "/imu", "/imu/data_raw", "/mavros/imu/data_raw", "/mavros/imu/data")
GYRO_BATCH = 1024


def add_arguments(p) -> None:
    from thermod.cli import import_flight

    p.add_argument("input", nargs="?", default=None,
                   help=".mcap file, rosbag2 directory or ROS 1 .bag; with --gyro a video or TIFF sequence")
    p.add_argument("-o", "--output", default=None, help="recording to write (HDF5, format v1)")
    p.add_argument(
        "--image-topic",
        default=None,
        help="sensor_msgs/Image topic of the raw frames "
        "(default: the only one, or a usual name such as /thermal/image_raw)",
    )
    p.add_argument(
        "--imu-topic",
        default=None,
        help="sensor_msgs/Imu topic of the gyro (default: the only one, or /imu/data)",
    )
    p.add_argument(
        "--camera-info-topic",
        default=None,
        help="sensor_msgs/CameraInfo topic (default: the one beside the image topic, or the only one)",
    )
    p.add_argument(
        "--calibration",
        default=None,
        metavar="TOML",
        help="a thermod TOML with a [calibration] "
        "table (e.g. thermod discrepancy's model.toml); its keys override the bag's; with --gyro a "
        "CAMERA.toml ([camera] or [calibration])",
    )
    p.add_argument(
        "--tau",
        type=float,
        default=None,
        metavar="S",
        help="detector time constant (s); needed when the calibration comes from CameraInfo; with "
        "--gyro it overrides the camera file's",
    )
    import_flight.add_arguments(p)


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


def _base_calibration(bag: mcap.Bag, info_topic: str | None, args) -> tuple[Calibration | None, str]:
    """What the bag says about the calibration before reading messages (thermod metadata), or None
    when it must come from CameraInfo; checks up front that nothing required is missing."""
    meta = bag.metadata.get(mcap.METADATA_NAME, {})
    if "calibration" in meta:
        try:
            return Calibration.from_dict(json.loads(meta["calibration"])), "thermod metadata"
        except (ValueError, TypeError, KeyError) as e:
            raise RecordingError(bag.path, "metadata thermod.calibration", f"unusable ({e})") from None
    if args.calibration is not None:
        return None, "calibration file"
    missing = []
    if info_topic is None:
        missing.append("camera intrinsics (no sensor_msgs/msg/CameraInfo topic)")
    if args.tau is None:
        missing.append("the detector time constant (--tau S)")
    if missing:
        raise ThermodError(
            f"{bag.path}: no thermod calibration in the bag; missing {' and '.join(missing)}: "
            "give --calibration model.toml (a [calibration] table) or those"
        )
    return None, "camera_info"


def _median_rate(t: list[float] | np.ndarray) -> float | None:
    dt = np.diff(np.asarray(t, np.float64))
    dt = dt[dt > 0]
    return float(1.0 / np.median(dt)) if len(dt) else None


def run(args) -> int:
    from thermod.cli import import_flight

    if args.list_cameras:
        from thermod.io.camera_file import preset_names

        print("\n".join(preset_names()))
        return 0
    if args.input is None or args.output is None:
        raise ThermodError("thermod import: expected INPUT and -o OUTPUT")
    if args.gyro is not None:
        return import_flight.run(args)
    from thermod.cli import import_video

    if import_video.is_video(args.input):     # a video with no gyro: the motion from the pictures
        return import_video.run(args)
    flight_only = [f"--{k.replace('_', '-')}" for k in ("camera", "fps", "log_index", "report", "duration")
                   if getattr(args, k) is not None] + (["--no-refine"] if args.no_refine else []) \
        + (["--start"] if args.start else [])
    if flight_only:
        raise ThermodError(f"{args.input}: {', '.join(flight_only)} apply to a flight import "
                           "(with --gyro LOG)")
    return _run_bag(args)


def _run_bag(args) -> int:
    from thermod.cli.record import RecordWriter

    out = Path(args.output)
    if not out.parent.is_dir():
        raise RecordingError(out, "file", f"directory {out.parent} does not exist")
    with mcap.Bag(args.input) as bag:
        image_topic = pick_topic(bag, mcap.IMAGE, args.image_topic, IMAGE_TOPICS, "image-topic")
        imu_topic = pick_topic(bag, mcap.IMU, args.imu_topic, IMU_TOPICS, "imu-topic")
        beside = image_topic.rsplit("/", 1)[0] + "/camera_info"
        info_topic = pick_topic(
            bag,
            mcap.CAMERA_INFO,
            args.camera_info_topic,
            (beside, mcap.CAMERA_INFO_TOPIC),
            "camera-info-topic",
            required=False,
        )
        base, source = _base_calibration(bag, info_topic, args)
        writer = RecordWriter(out)
        try:
            info, frame_t, gyro_t = _stream(bag, writer, image_topic, imu_topic, info_topic)
            calibration = _calibration(bag, base, info, frame_t, gyro_t, args)
            writer.finish(
                calibration,
                {
                    "imported_from": str(bag.path),
                    "image_topic": image_topic,
                    "imu_topic": imu_topic,
                    "imported_calibration": source,
                },
            )
        except BaseException:
            writer.discard()
            raise
    print(
        f"wrote {out}: {len(frame_t)} frames from {image_topic}, {len(gyro_t)} gyro samples from "
        f"{imu_topic}, "
        f"calibration from {source}" + (f" + {args.calibration}" if args.calibration else "")
    )
    return 0


def _stream(bag, writer, image_topic, imu_topic, info_topic):
    """Messages → writer; returns the first CameraInfo's intrinsics and the frame and gyro times."""
    info, frame_t, gyro_t = None, [], []
    batch = np.zeros(GYRO_BATCH, GYRO_DTYPE)
    n = 0
    topics = [t for t in (image_topic, imu_topic, info_topic) if t is not None]
    for topic, msg in bag.messages(topics):
        if topic == image_topic:
            image = mcap.image_array(msg, bag.path, topic)
            if image.dtype == np.float32:
                raise RecordingError(
                    bag.path,
                    topic,
                    "32FC1 frames are not raw detector counts; choose the raw image topic with --image-topic",
                )
            t = mcap.from_stamp(msg.header.stamp)
            writer.add("raw", {"t": t, "frame_id": len(frame_t)}, image.astype(np.uint16, copy=False))
            frame_t.append(t)
        elif topic == imu_topic:
            v = msg.angular_velocity
            batch[n] = (mcap.from_stamp(msg.header.stamp), (v.x, v.y, v.z))
            n += 1
            if n == GYRO_BATCH:
                writer.add("gyro", {"sample_seq": len(gyro_t)}, batch[:n].copy())
                gyro_t.extend(batch["t"][:n].tolist())
                n = 0
        elif info is None:
            info = mcap.camera_info_intrinsics(msg)
    if n:
        writer.add("gyro", {"sample_seq": len(gyro_t)}, batch[:n].copy())
        gyro_t.extend(batch["t"][:n].tolist())
    if not frame_t:
        raise RecordingError(bag.path, image_topic, "no frames")
    if sum(writer.dropped.values()):
        raise RecordingError(bag.path, image_topic, f"frames of varying size ({dict(writer.dropped)})")
    return info, frame_t, gyro_t


def _calibration(bag, base, info, frame_t, gyro_t, args) -> Calibration:
    if base is None and info is not None:
        if info["distorted"]:
            log.warning(
                "%s: CameraInfo declares lens distortion; thermod models a pinhole camera and ignores it",
                bag.path,
            )
        kw = {k: info[k] for k in ("width", "height", "fx", "fy", "cx", "cy")}
        if args.tau is not None:
            kw["tau_s"] = args.tau
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
    if args.calibration is not None:
        from thermod.io import calibration_file

        return calibration_file.load_calibration(args.calibration, base)
    return base
