"""`thermod import VIDEO --gyro LOG -o REC.h5`: a thermal video and a flight-controller log → a synced
format-v1 recording (`thermod.ingest.flight`).

The camera comes from ``--calibration CAMERA.toml`` (a ``[camera]`` or ``[calibration]`` table,
`thermod.io.camera_file`) or ``--camera PRESET`` (config/cameras/); one of the two is required, since
the focal length and τ are not in the video. ``--fps`` gives an image sequence's frame rate (TIFF
or PNG frames), ``--log-index`` picks one log of a multi-log file, ``--start``/``--duration`` import
a part of the video, ``--refine`` adds the discrepancy refinement (minutes on 2 cores; the sync alone
takes seconds) and ``--report DIR`` writes sync.json and sync.png.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from thermod.errors import ThermodError
from thermod.paths import directory_problem, input_problem, output_problem


def add_arguments(p) -> None:
    """The flight-import options, added to `thermod import`'s parser."""
    g = p.add_argument_group("flight import (with --gyro: INPUT is a thermal video or TIFF/PNG frames)")
    g.add_argument("--gyro", default=None, metavar="LOG",
                   help="flight-controller log: Betaflight .bbl/.bfl/.csv, ArduPilot .bin, PX4 .ulg, "
                        "Gyroflow .gcsv, …")
    g.add_argument("--camera", default=None, metavar="PRESET",
                   help="a camera preset instead of --calibration (thermod import --list-cameras)")
    g.add_argument("--list-cameras", action="store_true", help="list the camera presets and exit")
    g.add_argument("--fps", type=float, default=None, metavar="F",
                   help="frame rate of an image sequence (TIFF or PNG frames; a video file's own timestamps "
                   "are used)")
    g.add_argument("--log-index", type=int, default=None, metavar="N",
                   help="which log of a file holding several (0-based; default the longest)")
    g.add_argument("--start", type=float, default=0.0, metavar="S",
                   help="import the video from S seconds after its first frame (default 0)")
    g.add_argument("--duration", type=float, default=None, metavar="D",
                   help="import D seconds of video (default: to its end)")
    g.add_argument("--refine", action="store_true",
                   help="also refine offset, mount, bias, readout and τ with the discrepancy workflow on the "
                        "stretch that rotates most (minutes on 2 cores; the sync alone takes seconds)")
    g.add_argument("--no-refine", action="store_true", help="no refinement (the default; kept for scripts)")
    g.add_argument("--report", default=None, metavar="DIR", help="write sync.json and sync.png here")
    g.add_argument("--fit-tau", action="store_true",
                   help="without --gyro: fit the detector's τ to the frames' comet tails (also done when the "
                        "camera file gives no tau_s); a stated τ more than 3σ off is reported")


def camera(args, *, tau_required: bool = True):
    """The camera description from --calibration or --camera (exactly one); `tau_required` False lets
    a camera file leave τ out (the video-only import fits it)."""
    from thermod.io.camera_file import load_camera, preset_path

    if (args.calibration is None) == (args.camera is None):
        raise ThermodError(f"{args.input}: a flight import needs the camera: give exactly one of "
                           "--calibration CAMERA.toml or --camera PRESET")
    cam = load_camera(args.calibration if args.calibration is not None else preset_path(args.camera),
                      tau_required=tau_required)
    if args.tau is not None:
        if not 0 < args.tau <= 1:
            raise ThermodError(f"--tau {args.tau}: expected a time constant in (0, 1] s")
        cam = cam.replace(tau_s=float(args.tau))
    return cam


def checked_video_options(args) -> Path:
    """--fps, --start, --duration, -o and --report checked (the options both video imports share),
    before any work; the output."""
    if args.fps is not None and not args.fps > 0:
        raise ThermodError(f"--fps {args.fps}: expected a frame rate > 0 Hz")
    if not (math.isfinite(args.start) and args.start >= 0):
        raise ThermodError(f"--start {args.start}: expected 0 or more seconds after the video's first frame")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ThermodError(f"--duration {args.duration}: expected more than 0 seconds")
    out = Path(args.output)
    if (problem := output_problem(out)) is not None:
        raise ThermodError(f"-o {out}: {problem}")
    if args.report is not None and (problem := directory_problem(args.report)) is not None:
        raise ThermodError(f"--report {args.report}: {problem}")
    return out


def run(args) -> int:
    from thermod.ingest.flight import import_flight

    out = checked_video_options(args)
    if (problem := input_problem(args.gyro)) is not None:          # before minutes of reading the video
        raise ThermodError(f"--gyro {args.gyro}: {problem}")
    if args.log_index is not None and args.log_index < 0:
        raise ThermodError(f"--log-index {args.log_index}: expected 0 or more")
    if args.fit_tau:
        raise ThermodError(f"{args.input}: --fit-tau applies to a video imported without --gyro (with a "
                           "log, --refine fits τ)")
    if args.refine and args.no_refine:
        raise ThermodError(f"{args.input}: --refine and --no-refine contradict each other")
    cam = camera(args)
    r = import_flight(args.input, args.gyro, out, cam, fps=args.fps, log_index=args.log_index,
                      refine=args.refine, report_dir=args.report, start_s=args.start,
                      duration_s=args.duration,
                      say=lambda m: print(m, file=sys.stderr))
    for note in r.notes:
        print(f"note: {note}", file=sys.stderr)
    d = r.sync.to_dict()
    print(f"wrote {r.path}: {r.n_frames} frames, {r.n_gyro} gyro samples ({r.log_format}); "
          f"t_log = t_video {r.log_offset_s:+.4f} s (± {d['time_offset_s']['sigma'] * 1e3:.2f} ms), "
          f"mount {d['mount']}"
          + (f"; report in {args.report}" if args.report else ""))
    return 0
