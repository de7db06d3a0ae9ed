"""`thermod export REC.h5 --gcsv OUT.gcsv`: a recording's synced gyro for Gyroflow.

The rates are the calibrated camera-frame rates (`Calibration.gyro_to_camera`: bias removed, mount,
scale and clock applied; the camera frame of docs/design.md §2, x right, y down, z forward), with
the orientation string `thermod.io.flightlog.GCSV_ORIENTATION_OPENCV_CAMERA` that tells Gyroflow so.
Times are on the video's clock: for a recording made by `thermod import VIDEO --gyro LOG` the
imported video's own timestamps; for any other recording the first frame is at 0, as in the video
`thermod deblur --video` writes. Samples before 0 are left out (Gyroflow's time starts there). The
header carries the readout time (``frame_readout_time``, ms) and the frame rate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from thermod.errors import ThermodError
from thermod.paths import output_problem


def add_arguments(p) -> None:
    p.add_argument("input", type=Path, metavar="REC.h5", help="recording, format v1")
    p.add_argument("--gcsv", required=True, type=Path, metavar="OUT.gcsv",
                   help="write the synced gyro as a Gyroflow .gcsv")


def gcsv_series(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """(times on the video clock, camera-frame rates rad/s, header rows) of recording `path`."""
    from thermod.io.recording import Reader

    with Reader(path) as r:
        t_frames, gyro_t, gyro_rate, calib = r.t, r.gyro_t, r.gyro_rate, r.calibration
        imported = "video" in r.group_attrs().get("import", {})
        source = str(r.group_attrs().get("motion", {}).get("source", "gyro"))
    t, rate = calib.gyro_to_camera(gyro_t, gyro_rate)
    if not imported:
        if len(t_frames) == 0:
            raise ThermodError(f"{path}: camera/t: no frames; expected at least one, whose time is the "
                               "video clock's zero")
        t = t - t_frames[0]
    keep = t >= 0.0
    if np.count_nonzero(keep) < 2:
        raise ThermodError(f"{path}: fewer than 2 gyro samples from the first frame on; nothing to export")
    extra = {"frame_readout_time": f"{calib.readout_s * 1e3:.6g}", "frame_rate": f"{calib.frame_rate_hz:.6g}",
             "frame_width": calib.width, "frame_height": calib.height}
    if source != "gyro":        # estimated (thermod import VIDEO without --gyro): the file says so
        extra["motion_source"] = source
    return t[keep], rate[keep], extra


def run(args) -> int:
    from thermod.io import flightlog

    out = args.gcsv
    if (problem := output_problem(out)) is not None:     # before reading the recording
        raise ThermodError(f"--gcsv {out}: {problem}")
    t, rate, extra = gcsv_series(args.input)
    flightlog.write_gcsv(out, t, rate, orientation=flightlog.GCSV_ORIENTATION_OPENCV_CAMERA,
                         note=f"thermod export of {args.input.name}: camera-frame rates, video clock",
                         extra=extra)
    print(f"wrote {out}: {len(t)} gyro samples from {t[0]:.3f} s to {t[-1]:.3f} s (video clock), "
          f"camera frame, orientation {flightlog.GCSV_ORIENTATION_OPENCV_CAMERA}"
          + (f"; motion estimated from the {extra['motion_source']}, not measured by a gyro"
             if "motion_source" in extra else ""))
    return 0
