"""Simulated frame streams for the temporal solvers' tests (tests/physics/test_temporal.py and
test_recursive.py): a textured scene under a pan with the paper's gyro, and PSNR on the truth's 8-bit
scale."""

from __future__ import annotations

import math

import numpy as np

from thermod.physics.calibration import Calibration
from thermod.sim import motion as mo
from thermod.sim import synth
from thermod.sim.gyro_model import GyroErrorModel


def pan(deg_s: float, angle: float = 0.4) -> mo.Pan:
    """A pan at `deg_s` whose direction is `angle` (rad) off the yaw axis towards pitch."""
    w = math.radians(deg_s)
    return mo.Pan((w * math.sin(angle), w * math.cos(angle), 0.0), spec=f"pan:{deg_s:g}")


def stream(motion, n: int, calib: Calibration, netd: float, seed: int = 3, movers=(), **effects):
    """`n` frames of the seeded texture under `motion`, with truth."""
    return synth.simulate("texture", motion, seconds=n / calib.frame_rate_hz, calib=calib,
                          effects={"netd": netd, **effects}, seed=seed, gyro=GyroErrorModel.paper(),
                          movers=movers)


def psnr(est, truth, box=None) -> float:
    """PSNR (dB) on the 8-bit scale of the truth's 0.5–99.5 % range, over `box` if given."""
    lo, hi = np.percentile(truth, (0.5, 99.5))
    e = np.clip((est - lo) / (hi - lo), 0, 1) * 255
    t = np.clip((truth - lo) / (hi - lo), 0, 1) * 255
    if box is not None:
        e, t = e[box], t[box]
    return 10 * math.log10(255 ** 2 / float(np.mean((e - t) ** 2)))


def assert_no_ghost(x, s, truth, radius_px: float, track, now: int, before=(1, 2, 3)) -> None:
    """No ghost of a moving object in `x` (the temporal result) beside `s` (the single-frame one): where
    the object was `before` frames ago (`track(j)` → its centre (x, y) in frame `now`'s pixels at frame
    j), off where it is now, the residual is no larger than the single-frame one and does not correlate
    with its disc there."""
    H, W = truth.shape
    yy, xx = np.mgrid[:H, :W]
    cx, cy = track(now)
    here = np.hypot(xx - cx, yy - cy) < radius_px + 2
    for j in (now - b for b in before):
        px, py = track(j)
        disc = np.hypot(xx - px, yy - py) < radius_px + 1.5
        ring = np.hypot(xx - px, yy - py) < radius_px + 4
        sel = ring & ~here
        assert sel.sum() > 30
        rt, rs = (x - truth)[sel], (s - truth)[sel]
        assert np.abs(rt).mean() < 1.1 * np.abs(rs).mean() + 1.0
        corr = np.corrcoef(rt, disc[sel].astype(float))[0, 1]
        assert corr < 0.1, (j, corr)
