"""Gyro-side effects (clock_drift, gyro_lowpass, gyro_saturation): fitted by `thermod discrepancy`, then
deblurred with the fitted model and with the nominal one; PSNR against the simulator's sharp truth.

    python benchmarks/bench_gyro_effects.py [--quick]

Recordings: the simulator's fine-time renderer, 320×240 at 50 Hz, 0.2 s static then 0.3 s of three-axis
shake (plus a 10 Hz vibration for the low-pass: its attenuation needs content near the cutoff), NETD
50 mK, the seeded procedural texture. Deblurring: the thermal kernel (Eq. 18) at the image centre and a
Wiener-type deconvolution (`deconv.deconvolve(method="kf")`) of the motion frames, 24 px border left out.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from thermod.calib import discrepancy as D
from thermod.physics import deconv, kernels
from thermod.physics.calibration import Calibration
from thermod.sim import motion as mo
from thermod.sim.synth import simulate, truth_calibration

_I = Calibration().intrinsics.scaled(0.5)
NOMINAL = Calibration(width=320, height=240, fx=_I.fx, fy=_I.fy, cx=_I.cx, cy=_I.cy)


def motion(broadband: bool, seed: int = 3) -> mo.Motion:
    inner = mo.shake(2.0, seed)
    if broadband:
        inner = mo.Summed(inner, mo.vibration(15.0, 10.0, seed))
    return mo.sequence([(mo.static(), 0.2), (inner, None)])


CASES = {   # effect: (hidden effects, broadband motion, the parameter to report)
    "clock_drift": ({"clock_drift": 10000.0}, False, "clock_drift_ppm"),
    "gyro_lowpass": ({"gyro_lowpass": 20.0}, True, "gyro_lowpass_hz"),
    "gyro_saturation": ({"gyro_saturation": 0.7}, False, "gyro_range_rad_s"),
}


def psnr(rec, cal: Calibration, frames) -> float:
    m = 24
    out = []
    for k in frames:
        ref = rec.extras["truth/frames"][k][m:-m, m:-m]
        ker = kernels.render_thermal_kernel(rec.gyro_t, rec.gyro_rate, cal, float(rec.t[k]))
        img = deconv.deconvolve(rec.frames[k].astype(np.float32), ker, method="kf")
        peak = float(ref.max() - ref.min())
        out.append(10 * math.log10(peak**2 / float(np.mean((img[m:-m, m:-m] - ref) ** 2))))
    return float(np.mean(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one effect (clock_drift)")
    ap.add_argument("--only", choices=list(CASES), help="one effect")
    ap.add_argument("-v", "--verbose", action="store_true", help="the analysis's progress")
    args = ap.parse_args()
    names = [args.only] if args.only else ["clock_drift"] if args.quick else list(CASES)
    print("| effect | true | recovered | named | gap before → after | noise floor | PSNR nominal | "
          "PSNR fitted | PSNR truth | analysis s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        fx, broad, key = CASES[name]
        rec = simulate("texture", motion(broad), 0.5, NOMINAL, {"netd": 0.05, **fx}, seed=1)
        t0 = time.monotonic()
        ana = D.analyse([D.prepare(rec, NOMINAL, name=name)], D.Model(NOMINAL),
                        progress=print if args.verbose else None)
        dt = time.monotonic() - t0
        truth = truth_calibration(rec)
        frames = range(14, 25)                        # 80 ms or more into the motion
        cals = {"nominal": NOMINAL, "fitted": ana.model.final_calibration(), "truth": truth}
        p = {lab: psnr(rec, c, frames) for lab, c in cals.items()}
        print(f"| {name} | {getattr(truth, key):.4g} | {getattr(ana.model.calib, key):.4g} | "
              f"{', '.join(ana.named) or '–'} | {ana.gap_initial:.4f} → {ana.gap_final:.4f} | "
              f"{ana.noise_floor:.4f} | {p['nominal']:.2f} | {p['fitted']:.2f} | {p['truth']:.2f} | "
              f"{dt:.0f} |", flush=True)


if __name__ == "__main__":
    main()
