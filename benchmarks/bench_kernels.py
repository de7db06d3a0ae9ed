"""Speed of the blur-kernel renderer (Eq. 18) against its plain NumPy reference, same run.

The reference is thermod.sim.reference_kernels (independent of the renderer's code).

    .venv/bin/python benchmarks/bench_kernels.py [--repeats N]

Cases (the paper's camera: 640×480, IFOV 0.0391°, τ = 8 ms, 1 kHz gyro, PSF on):
  uniform-40    one kernel from the 40 samples of a 5τ window, 30 °/s pan      target ≤ 50 µs
  grid-6x8      48 kernels over the frame, mixed roll/pitch/yaw motion          target ≤ 2 ms
  pan-100dps    one 100+ px kernel, 100 °/s                                     (no target)
  ring-1h       uniform-40 read from a one-hour 1 kHz ring (only the window is touched)
  blur-640x480  the forward model with the 100 °/s kernel (cv2.filter2D)        (no target)
  blur-varying  the spatially varying forward model over the 6×8 grid          (no target)
Prints medians (and the 10th–90th percentile spread) and the reference/fast ratio.
"""

from __future__ import annotations

import argparse
import math
import os
import time

os.environ.setdefault("NUMBA_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".numba_cache"))

import numpy as np  # noqa: E402

from thermod.physics import kernels as K  # noqa: E402
from thermod.physics.calibration import Calibration  # noqa: E402
from thermod.sim.reference_kernels import render_thermal_kernel_reference  # noqa: E402


def timeit(fn, repeats: int, inner: int = 1) -> np.ndarray:
    """Seconds per call, one entry per repeat (each the mean of `inner` back-to-back calls)."""
    fn()   # warm up (numba compile / cache load)
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        out[i] = (time.perf_counter() - t0) / inner
    return out


def fmt(seconds: float) -> str:
    if seconds < 1e-3:
        return f"{seconds * 1e6:8.1f} µs"
    if seconds < 1.0:
        return f"{seconds * 1e3:8.2f} ms"
    return f"{seconds:8.2f} s "


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=200, help="timed repeats of the fast renderer")
    ap.add_argument("--ref-repeats", type=int, default=15, help="timed repeats of the NumPy reference")
    args = ap.parse_args(argv)

    cal = Calibration()
    t = np.arange(0.0, 0.2, 1e-3)
    tf = 0.1004
    pan30 = np.tile(np.float32([0.0, math.radians(30), 0.0]), (len(t), 1))
    pan100 = np.tile(np.float32([0.0, math.radians(100), 0.0]), (len(t), 1))
    mixed = np.stack([0.5 * np.sin(30 * t), 0.8 * np.cos(21 * t) + 0.2, 0.6 * np.sin(13 * t)], 1)
    mixed = mixed.astype(np.float32)
    img = np.random.default_rng(0).uniform(0, 1000, (cal.height, cal.width)).astype(np.float32)
    k100 = K.render_thermal_kernel(t, pan100, cal, tf)
    grid = K.render_kernel_grid(t, mixed, cal, tf, (6, 8))
    t_ring = np.arange(0.0, 3600.0, 1e-3)
    pan_ring = np.tile(np.float32([0.0, math.radians(30), 0.0]), (len(t_ring), 1))

    cases = [
        ("uniform-40", 50e-6,
         lambda: K.render_thermal_kernel(t, pan30, cal, tf),
         lambda: render_thermal_kernel_reference(t, pan30, cal, tf), 50),
        ("grid-6x8", 2e-3,
         lambda: K.render_kernel_grid(t, mixed, cal, tf, (6, 8)),
         lambda: [render_thermal_kernel_reference(t, mixed, cal, tf, point=(x, y))
                  for y in np.linspace(39.5, 439.5, 6) for x in np.linspace(39.5, 599.5, 8)], 2),
        ("pan-100dps", None,
         lambda: K.render_thermal_kernel(t, pan100, cal, tf),
         lambda: render_thermal_kernel_reference(t, pan100, cal, tf), 20),
        ("ring-1h", 50e-6, lambda: K.render_thermal_kernel(t_ring, pan_ring, cal, 1800.0004), None, 50),
        ("blur-640x480", None, lambda: K.blur(img, k100), None, 1),
        ("blur-varying", None, lambda: K.blur_varying(img, grid), None, 1),
    ]
    print(f"kernel renderer: {cal.width}×{cal.height}, τ = {cal.tau_s * 1e3:.0f} ms, "
          f"{cal.rate_hz:.0f} Hz gyro, PSF σ = {cal.psf_sigma_px:.3f} px, step ≤ {K.MAX_STEP_PX} px; "
          f"100 °/s kernel {k100.weights.shape[1]}×{k100.weights.shape[0]} px")
    head = f"{'case':<14}{'median':>12}{'p10–p90':>24}{'target':>12}{'ok':>5}{'NumPy ref':>14}{'ratio':>9}"
    print(head)
    print("-" * len(head))
    for name, target, fast, ref, inner in cases:
        ts = timeit(fast, args.repeats, inner)
        med = float(np.median(ts))
        spread = f"{fmt(np.percentile(ts, 10)).strip()}–{fmt(np.percentile(ts, 90)).strip()}"
        tgt = fmt(target) if target else "—"
        ok = ("yes" if med <= target else "NO") if target else ""
        if ref is not None:
            rmed = float(np.median(timeit(ref, args.ref_repeats)))
            rtxt, ratio = fmt(rmed), f"{rmed / med:7.0f}×"
        else:
            rtxt, ratio = "—", ""
        print(f"{name:<14}{fmt(med):>12}{spread:>24}{tgt:>12}{ok:>5}{rtxt:>14}{ratio:>9}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
