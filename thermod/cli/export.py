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
    _check_gcsv_range(path, t[keep], rate[keep], imported)
    extra = {"frame_readout_time": f"{calib.readout_s * 1e3:.6g}", "frame_rate": f"{calib.frame_rate_hz:.6g}",
             "frame_width": calib.width, "frame_height": calib.height}
    if source != "gyro":        # estimated (thermod import VIDEO without --gyro): the file says so
        extra["motion_source"] = source
    return t[keep], rate[keep], extra


# What a .gcsv holds (`flightlog.write_gcsv`: integer µs and µrad/s, exact in float64 up to 2⁵³)
GCSV_TICK_S, GCSV_LSB_RAD_S = 1e-6, 1e-6
GCSV_MAX_T_S = 1e9                       # 31 years of video clock
GCSV_MAX_RATE_RAD_S = 2.0**53 * GCSV_LSB_RAD_S


def _check_gcsv_range(path, t: np.ndarray, rate: np.ndarray, imported: bool) -> None:
    """The synced series fits a .gcsv, else an error naming the recording's field: times within
    `GCSV_MAX_T_S` of the video clock's zero and at least a tick apart, rates within its integers."""
    zero = "the imported video's start" if imported else "the first frame (camera/t[0])"
    if not t[-1] <= GCSV_MAX_T_S:
        raise ThermodError(f"{path}: gyro/t: samples run to {t[-1]:.6g} s after {zero}; a .gcsv holds "
                           f"times within {GCSV_MAX_T_S:g} s of it")
    ticks = np.round(t / GCSV_TICK_S)
    if np.any(same := np.diff(ticks) <= 0):
        i = int(np.flatnonzero(same)[0])
        raise ThermodError(f"{path}: gyro/t: samples {i} and {i + 1} from {zero} on are "
                           f"{t[i + 1] - t[i]:.3g} s apart (calibrated); a .gcsv counts whole "
                           f"{GCSV_TICK_S * 1e6:g} µs ticks")
    big = np.abs(rate) > GCSV_MAX_RATE_RAD_S
    if np.any(big):
        i = int(np.flatnonzero(big.any(axis=1))[0])
        raise ThermodError(f"{path}: gyro/rate: the calibrated camera-frame rate at sample {i} from {zero} "
                           f"on is {np.abs(rate[i]).max():.4g} rad/s (from gyro/rate and the gyro attributes "
                           f"bias_rad_s, scale); a .gcsv holds at most {GCSV_MAX_RATE_RAD_S:.4g}")


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
