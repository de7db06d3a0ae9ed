"""Synthetic blur kernels of known shape, for tests and benchmarks of the deconvolution."""

from __future__ import annotations

import math

import numpy as np

from thermod.physics.kernels import Kernel


def comet(length: int, decay: float, angle_deg: float = 0.0) -> Kernel:
    """One-sided exponential streak (thermal-like: the detector's lag leaves a fading tail) of ``length``
    px at ``angle_deg``, weight exp(−s/decay) at distance s, bilinear splats, origin at the head."""
    size = 2 * length + 1
    w = np.zeros((size, size), np.float64)
    c = length
    a = math.radians(angle_deg)
    for s in np.linspace(0, length - 1, 8 * length):
        x, y = c - s * math.cos(a), c - s * math.sin(a)
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        wt = math.exp(-s / decay)
        w[y0, x0] += wt * (1 - fx) * (1 - fy)
        w[y0, x0 + 1] += wt * fx * (1 - fy)
        w[y0 + 1, x0] += wt * (1 - fx) * fy
        w[y0 + 1, x0 + 1] += wt * fx * fy
    ys, xs = np.nonzero(w)
    w = w[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
    return Kernel((w / w.sum()).astype(np.float32), (c - ys.min(), c - xs.min()))
