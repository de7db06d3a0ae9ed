"""`thermod import VIDEO -o REC.h5 --camera PRESET | --calibration CAMERA.toml` with no ``--gyro``: a thermal
video alone → a format-v1 recording whose gyro is the camera's rotation estimated from the pictures
(`thermod.ingest.video_only`). The options are the flight import's (``--fps``, ``--start``,
``--duration``, ``--report DIR`` for track.json and track.png); ``--tau`` overrides the camera file's τ,
``--fit-tau`` fits τ to the frames' comet tails (as when the camera file gives none).
"""

from __future__ import annotations

import sys
from pathlib import Path

from thermod.errors import ThermodError

VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov", ".avi", ".m4v", ".ts", ".mts", ".m2ts", ".webm", ".mpg", ".mpeg",
                  ".h264", ".264", ".hevc", ".h265", ".nut", ".mxf", ".flv", ".3gp", ".y4m", ".ogv", ".wmv",
                  ".asf", ".mjpeg", ".mjpg", ".gif", ".apng", ".tif", ".tiff")


def is_video(path: str) -> bool:
    """A video file or an image sequence (a glob, or a folder of TIFF or PNG frames) rather than a
    ROS recording."""
    from thermod.io.video import SEQUENCE_SUFFIXES

    p = Path(path)
    if any(ch in str(path) for ch in "*?["):
        return True
    if p.is_dir():
        return any(q.suffix.lower() in SEQUENCE_SUFFIXES for q in p.iterdir())
    return p.suffix.lower() in VIDEO_SUFFIXES


def run(args) -> int:
    from thermod.cli.import_flight import camera, checked_video_options
    from thermod.ingest.video_only import import_video
    from thermod.io.camera_file import states_tau

    other = [f"--{k.replace('_', '-')}" for k in ("log_index", "image_topic", "imu_topic",
                                                  "camera_info_topic") if getattr(args, k, None) is not None]
    other += [f for f, on in (("--refine", args.refine), ("--no-refine", args.no_refine)) if on]
    if other:
        raise ThermodError(f"{args.input}: {', '.join(other)} do not apply to a video imported without "
                           "--gyro")
    if (args.calibration is None) == (args.camera is None):
        raise ThermodError(f"{args.input}: importing a video without --gyro needs the camera (focal length "
                           "and τ are not in the video): give exactly one of --calibration CAMERA.toml or "
                           "--camera PRESET")
    out = checked_video_options(args)
    tau_stated = args.tau is not None or args.calibration is None or states_tau(args.calibration)
    r = import_video(args.input, out, camera(args, tau_required=False), fps=args.fps, start_s=args.start,
                     duration_s=args.duration, report_dir=args.report, fit_time_constant=args.fit_tau,
                     tau_stated=tau_stated, say=lambda m: print(m, file=sys.stderr))
    for note in r.notes:
        print(f"note: {note}", file=sys.stderr)
    print(f"wrote {r.path}: {r.n_frames} frames, {r.n_gyro} gyro samples estimated from the video "
          f"(motion source: video, lag {r.track.lag_s * 1e3:.1f} ms)"
          + (f"; report in {args.report}" if args.report else ""))
    return 0
