"""A plain NumPy thermal-kernel renderer (Eq. 16/18/19) that the numba one is held to.

Written from the documented maths and the `Calibration` fields only: it imports nothing from
`thermod.physics.kernels` but the `Kernel` container, so a bug in the renderer's parameters
(window, row time, image-speed bound, node spacing, PSF taps, calibration mapping) shows up as a
difference. It shares the geometry's rotation integrator (`integrate_rotations`, `so3_exp`), which
tests/physics/test_geometry.py pins against the matrix exponential. Slow: for tests and benchmarks.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import convolve2d

from thermod.physics.calibration import Calibration
from thermod.physics.geometry import apply_homography, integrate_rotations, so3_exp
from thermod.physics.kernels import Kernel

#: The renderer's documented node spacing (px): < 0.5 px against stepping (Eq. 12), 0.25 px keeps the
#: splat ripple below ~2 %. Restated here, not imported, so a changed constant is noticed.
NODE_SPACING_PX = 0.25


def _speed_bound_px_per_rad(c: Calibration, x: float, y: float) -> float:
    """The documented bound on image speed per rad/s: f·(1 + ρ²)·1.05, ρ the largest normalised
    radius of the frame's outer pixel edges or of (x, y), plus 0.05."""
    rx = max(c.cx + 0.5, c.width - 0.5 - c.cx, abs(x - c.cx)) / c.fx
    ry = max(c.cy + 0.5, c.height - 0.5 - c.cy, abs(y - c.cy)) / c.fy
    rho = math.hypot(rx, ry) + 0.05
    return max(c.fx, c.fy) * (1.0 + rho * rho) * 1.05


def _gaussian_taps(sigma: float) -> np.ndarray:
    r = max(1, math.ceil(3.0 * sigma))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def render_thermal_kernel_reference(gyro_t, gyro_rate, calib: Calibration, t_frame: float, *, point=None,
                                    m: float = 5.0, psf: bool = True) -> Kernel:
    """Same signature and result as `thermod.physics.kernels.render_thermal_kernel`."""
    c = calib
    x, y = (c.cx, c.cy) if point is None else (float(point[0]), float(point[1]))
    tau = float(c.tau_s)
    b = float(t_frame) - c.readout_s * (1.0 - (y + 1.0) / c.height)    # the read time of row y
    a = b - m * tau
    # the gyro samples covering [a, b] (camera clock) and one more each side, calibrated
    t_all = np.asarray(gyro_t, np.float64)
    tc_all = t_all + c.time_offset_s
    i0 = max(int(np.searchsorted(tc_all, a, side="right")) - 1, 0)
    i1 = min(int(np.searchsorted(tc_all, b, side="left")) + 1, len(t_all))
    if i1 <= i0:
        i0, i1 = (len(t_all) - 1, len(t_all)) if i0 >= len(t_all) - 1 else (0, 1)
    tc, wc = c.gyro_to_camera(t_all[i0:i1], np.asarray(gyro_rate)[i0:i1])
    Qs = integrate_rotations(tc, wc, b)

    def rate(s):
        return np.array([np.interp(s, tc, wc[:, i]) for i in range(3)])

    inside = (tc > a) & (tc < b)
    bt = np.r_[a, tc[inside], b]
    bQ = [None] + [Qs[i] for i in np.nonzero(inside)[0]] + [np.eye(3)]
    ppr = _speed_bound_px_per_rad(c, x, y)
    times, Qn = [], []
    for k in range(len(bt) - 1):
        s0, s1 = bt[k], bt[k + 1]
        w0, w1 = rate(s0), rate(s1)
        move = ppr * max(np.linalg.norm(w0), np.linalg.norm(w1)) * (s1 - s0)
        n = max(1, int(math.ceil(move / NODE_SPACING_PX)))
        for j in range(n):
            s = s0 + (s1 - s0) * j / n
            times.append(s)
            Qn.append(bQ[k + 1] @ so3_exp(-0.5 * (rate(s) + w1) * (s1 - s)))
    times.append(b)
    Qn.append(np.eye(3))
    times = np.asarray(times)
    # ∫ e(s)(1−λ) ds and ∫ e(s) λ ds over each sub-interval, e(s) = exp(−(b − s)/τ)
    x0, x1 = times[:-1], times[1:]
    h = x1 - x0
    e0, e1 = np.exp(-(b - x0) / tau), np.exp(-(b - x1) / tau)
    total = tau * (e1 - e0)
    with np.errstate(invalid="ignore", divide="ignore"):
        right = np.where(h / tau > 1e-3, tau * e1 - tau * tau * (e1 - e0) / h,
                         tau * e0 * (0.5 * (h / tau) + (h / tau) ** 2 / 3 + (h / tau) ** 3 / 8))
    w = np.zeros(len(times))
    w[:-1] += total - right
    w[1:] += right
    w /= w.sum()
    # offsets u = p − π(K Q K⁻¹ p) (Eq. 16) and the bilinear splat
    K = c.K
    pt = np.array([[x, y]])
    u = np.array([pt[0] - apply_homography(K @ Q @ np.linalg.inv(K), pt)[0] for Q in Qn])
    fl = np.floor(u)
    f = u - fl
    snap = f > 1 - 1e-9
    fl[snap] += 1
    f[snap] = 0
    f[f < 1e-9] = 0
    fl = fl.astype(int)
    need1 = f > 0
    xmin, ymin = fl[:, 0].min(), fl[:, 1].min()
    xmax = (fl[:, 0] + need1[:, 0]).max()
    ymax = (fl[:, 1] + need1[:, 1]).max()
    k = np.zeros((ymax - ymin + 1, xmax - xmin + 1))
    X, Y = fl[:, 0] - xmin, fl[:, 1] - ymin
    fx, fy = f[:, 0], f[:, 1]
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            val = w * wy * wx
            sel = val > 0
            np.add.at(k, (Y[sel] + dy, X[sel] + dx), val[sel])
    k /= k.sum()
    oy, ox = -ymin, -xmin
    sigma = 0.45 * c.wavelength_um * c.f_number / c.psf_beta / c.pixel_pitch_um   # Eq. 19, in px
    if psf and sigma > 0:
        g = _gaussian_taps(sigma)
        k = convolve2d(k, np.outer(g, g), mode="full")
        oy, ox = oy + len(g) // 2, ox + len(g) // 2
    lo, hi = max(a, tc[0]), min(b, tc[-1])
    cov = 0.0 if hi <= lo else (np.exp(-(b - hi) / tau) - np.exp(-(b - lo) / tau)) / -np.expm1(-(b - a) / tau)
    ns = int(((tc > a) & (tc <= b)).sum())
    return Kernel(k.astype(np.float32), (int(oy), int(ox)), float(min(cov, 1.0)), ns)
