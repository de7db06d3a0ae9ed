"""`thermod import IN -o OUT.h5`: a ROS recording (MCAP, rosbag2 directory, ROS 1 .bag) → format v1
(`thermod.ingest.bag`); with ``--gyro LOG``, IN is a thermal video synced to a flight-controller log
(`thermod.cli.import_flight`, `thermod.ingest.flight`); a video without ``--gyro`` gets a gyro
estimated from its pictures (`thermod.cli.import_video`, `thermod.ingest.video_only`). The
calibration, in order of precedence: ``--calibration model.toml`` (its [calibration] keys), the
``thermod`` metadata of an MCAP written by thermod, a sensor_msgs/CameraInfo topic plus ``--tau``
(the detector time constant, which no ROS message carries). An MCAP file cut short (the
``.mcap.part`` a killed `thermod record -o X.mcap` leaves) gives its complete messages, with a
warning, and the calibration its recorder wrote as soon as it received it (``--calibration`` is
needed only when it was killed before that).
"""

from __future__ import annotations

from pathlib import Path

from thermod.errors import ThermodError


def add_arguments(p) -> None:
    from thermod.cli import import_flight

    p.add_argument("input", nargs="?", default=None,
                   help=".mcap file (or the .mcap.part of a killed `thermod record`: its complete "
                   "messages), rosbag2 directory or ROS 1 .bag; with --gyro a video or TIFF/PNG frames")
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

    flight_only = [f"--{k.replace('_', '-')}" for k in ("camera", "fps", "log_index", "report", "duration")
                   if getattr(args, k) is not None]
    flight_only += [flag for flag, on in (("--refine", args.refine), ("--no-refine", args.no_refine),
                                          ("--start", bool(args.start)), ("--fit-tau", args.fit_tau)) if on]
    # a video with no gyro: the motion from the pictures; a folder given video options is taken for
    # image frames, so one without any is refused as such (not as a ROS bag)
    if import_video.is_video(args.input) or (flight_only and Path(args.input).is_dir()):
        return import_video.run(args)
    if flight_only:
        raise ThermodError(f"{args.input}: {', '.join(flight_only)} apply to a flight import "
                           "(with --gyro LOG)")
    return _run_bag(args)


def _run_bag(args) -> int:
    from thermod.ingest.bag import import_bag

    done = import_bag(args.input, args.output, image_topic=args.image_topic, imu_topic=args.imu_topic,
                      camera_info_topic=args.camera_info_topic, calibration=args.calibration, tau_s=args.tau)
    print(f"wrote {done.path}: {done.frames} frames from {done.image_topic}, {done.gyro_samples} gyro "
          f"samples from {done.imu_topic}, calibration from {done.calibration_source}"
          + (f" + {args.calibration}" if args.calibration else ""))
    return 0
