"""`thermod sim`: write a simulated recording (format v1) with known truth.

    thermod sim -o rec.h5 --scene real:3 --motion static:0.3+pan:50 --seconds 2 \\
        --effect time_offset=0.004 --effect rolling_readout=0.012 --gyro paper

The file's calibration attributes are the NOMINAL ones (from --width/--height/--fps/--tau/…);
each --effect changes the hidden truth (stored under /truth). Vector effects take comma-separated
values: --effect gyro_bias=0.001,0,-0.002.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from thermod.errors import ThermodError
from thermod.physics.calibration import Calibration
from thermod.physics.detector import DEFAULT_NETD_K  # temporal noise unless --effect netd=… says otherwise


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", required=True, help="recording to write (.h5)")
    p.add_argument("--scene", default="texture",
                   help="bars | points | texture | real[:N] | PATH to a 16-bit PNG (default texture)")
    p.add_argument("--motion", default="pan:50",
                   help="pan:50[:axis] | roll:30 | slew:90 | shake:2 | vibration[:rms[:hz]] | sway | "
                        "log[:start_s] | static; sequences with +, e.g. static:0.3+pan:50 (default pan:50)")
    p.add_argument("--seconds", type=float, default=1.0, help="duration (s, default 1)")
    p.add_argument("--effect", action="append", default=[], metavar="NAME=VALUE",
                   help="hidden truth effect (repeatable), e.g. time_offset=0.004, rolling_readout=0.012, "
                        "gyro_bias=0.001,0,0, misalignment=0,0,0.01, time_constant=0.010, netd=0.03 "
                        f"(temporal noise, K RMS; default {DEFAULT_NETD_K:g}, a typical uncooled core's "
                        "NETD; netd=0: noiseless); "
                        "gyro side: clock_drift=PPM (clocks agree at the first frame), gyro_lowpass=HZ "
                        "(2nd-order Butterworth DLPF cutoff), gyro_saturation=RAD_S (full-scale range); "
                        "detector side: detector_nonlinearity=0.3 (quadratic response, 1/1000 counts), "
                        "ffc_event=T_START,DURATION[,STEP_COUNTS] (frozen frames, then a new NUC); "
                        "outside the calibration model: parallax=HEIGHT_M,SPEED_M_S (flat ground below a "
                        "translating camera)")
    p.add_argument("--seed", type=int, default=0, help="random seed (scene, shake, noise)")
    p.add_argument("--width", type=int, default=None, help="image width (px, default 640)")
    p.add_argument("--height", type=int, default=None, help="image height (px, default 480)")
    p.add_argument("--fps", type=float, default=None, help="frame rate (Hz, default 50)")
    p.add_argument("--tau", type=float, default=None,
                   help="nominal detector time constant (s, default 0.008)")
    p.add_argument("--ifov-deg", type=float, default=None, help="angular pixel size (°, default 0.0391)")
    p.add_argument("--gyro-rate", type=float, default=None, help="gyro output rate (Hz, default 1000)")
    p.add_argument("--gyro", default="ideal", choices=("ideal", "paper"),
                   help="gyro error model: ideal, or the paper's Table 1 MEMS gyro (default ideal)")
    p.add_argument("--detector", default="thermal", choices=("thermal", "photon"),
                   help="microbolometer (thermal) or box-exposure photon detector")
    p.add_argument("--exposure", type=float, default=None, help="photon detector exposure (s)")
    p.add_argument("--step-px", type=float, default=0.5, help="max image motion per fine step (px, Eq. 12)")
    p.add_argument("--time-compression", type=float, default=None, metavar="C",
                   help="the paper's synthesis instead of the fine-time renderer: sharp views of a camera "
                        "C× slower, re-timed (thermal detector, no rolling readout)")
    p.add_argument("--slow-fps", type=float, default=50.0, help="frame rate of that slow camera (Hz)")
    p.add_argument("--no-truth", action="store_true", help="leave out the float32 truth frame stacks")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def parse_effects(items: list[str]) -> dict:
    out = {}
    for item in items:
        name, eq, val = item.partition("=")
        name = name.strip()
        if not eq or not name or not val.strip():
            raise ThermodError(f"--effect {item!r}: expected NAME=VALUE, e.g. time_offset=0.004")
        try:
            vals = [float(v) for v in val.split(",")]
        except ValueError:
            raise ThermodError(f"--effect {item!r}: value must be a number or comma-separated "
                               "numbers") from None
        if not all(math.isfinite(v) for v in vals):
            raise ThermodError(f"--effect {item!r}: value must be finite")
        out[name] = vals[0] if len(vals) == 1 else tuple(vals)
    return out


def build_calibration(args) -> Calibration:
    c = Calibration()
    kw = {}
    for opt, key in (("width", "width"), ("height", "height")):
        v = getattr(args, opt)
        if v is not None:
            if not 8 <= v <= 8192:
                raise ThermodError(f"--{opt}: expected 8–8192 px, got {v}")
            kw[key] = int(v)
    if args.ifov_deg is not None:
        if not 0 < args.ifov_deg < 10:
            raise ThermodError(f"--ifov-deg: expected 0 < IFOV < 10°, got {args.ifov_deg}")
        kw["fx"] = kw["fy"] = 1.0 / math.radians(args.ifov_deg)
    if args.tau is not None:
        if not 0 <= args.tau <= 1:
            raise ThermodError(f"--tau: expected 0–1 s, got {args.tau}")
        kw["tau_s"] = float(args.tau)
    if args.gyro_rate is not None:
        if not 1 <= args.gyro_rate <= 100000:
            raise ThermodError(f"--gyro-rate: expected 1–100000 Hz, got {args.gyro_rate}")
        kw["rate_hz"] = float(args.gyro_rate)
    c = c.replace(**kw)
    return c.replace(cx=(c.width - 1) / 2.0, cy=(c.height - 1) / 2.0)


def run(args) -> int:
    from thermod.io import recording
    from thermod.sim.gyro_model import GyroErrorModel
    from thermod.sim.synth import simulate

    out = Path(args.output)
    if not out.parent.exists():
        raise ThermodError(f"-o {out}: directory {out.parent} does not exist")
    calib = build_calibration(args)
    gyro = GyroErrorModel.paper() if args.gyro == "paper" else GyroErrorModel()
    t0 = time.perf_counter()
    effects = {"netd": DEFAULT_NETD_K, **parse_effects(args.effect)}
    rec = simulate(args.scene, args.motion, args.seconds, calib, effects=effects,
                   seed=args.seed, frame_rate=args.fps, gyro=gyro, progress=not args.no_progress,
                   kind=args.detector, exposure_s=args.exposure, step_px=args.step_px,
                   truth=not args.no_truth,
                   method="fine" if args.time_compression is None else "time_compression",
                   compression=args.time_compression or 20.0, slow_fps=args.slow_fps)
    recording.write(out, rec)
    dt = time.perf_counter() - t0
    truth = rec.extra_attrs["truth"]
    print(f"{out}: {rec.n_frames} frames {rec.calibration.width}×{rec.calibration.height} at "
          f"{rec.calibration.frame_rate_hz:g} Hz, {len(rec.gyro_t)} gyro samples, "
          f"{truth['n_steps']} fine steps, effects: {truth['effects'] or 'none'} ({dt:.1f} s)")
    return 0
