"""Blur kernels from the gyro: thermal (Eq. 18), photon (Eq. 17), optical PSF (Eq. 19), grids.

A microbolometer frame read at t_k is the exponential average of the sharp views S(s) over the
past (Eq. 11), so for a pure camera rotation it is the sharp view at t_k blurred by

    B(p) = Σ_u k(u) S_k(p − u),   k(u) = ∫ w(s) δ(u − u(s)) ds,   w(s) ∝ exp(−(t_k − s)/τ),

with u(s) = p − π(K Q(s) K⁻¹ p) and Q(s) = R(t_k)ᵀ R(s) (Eq. 16). The gyro gives ω at ~1 kHz;
between samples the rate is piecewise linear (exactly `thermod.physics.geometry.integrate_rotations`).
The path is subdivided so that consecutive splats are < 0.5 px apart — splatting only at the gyro
stamps would give a dotted kernel at high rates ("stepping", Eq. 12) — and each sub-interval's
weight is the exact integral of the exponential (or of the box, for a photon detector, Eq. 17)
against the linear "hat" between its end points, so a straight path gets its exact first moment.
Each node is splatted bilinearly, the kernel is normalised to 1 and optionally convolved with the
optical PSF (Eq. 19). Kernels are as large as the motion needs: never cropped.

`render_thermal_kernel` runs in numba; `render_thermal_kernel_reference` is a plain NumPy
re-implementation (built on `integrate_rotations`) that the tests hold the fast one to.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from thermod.errors import ThermodError
from thermod.physics.calibration import Calibration
from thermod.physics.geometry import apply_homography, integrate_rotations, so3_exp

__all__ = [
    "Kernel", "KernelGrid", "KernelPath", "KernelError",
    "render_thermal_kernel", "render_photon_kernel", "render_kernel_grid", "render_path",
    "render_thermal_kernel_reference", "optical_psf", "blur", "blur_varying", "row_time",
]

#: Largest spacing between consecutive splats along the path (px); < 0.5 px avoids stepping (Eq. 12),
#: 0.25 keeps the bilinear-splat ripple along a fast path below ~2 %.
MAX_STEP_PX = 0.25
#: Refuse paths needing more nodes than this (a garbage rate, not a real motion).
MAX_NODES = 2_000_000


class KernelError(ThermodError, ValueError):
    """Bad input to a kernel renderer (names the argument), or a motion no kernel can represent."""


# ------------------------------------------------------------------------------------------ types
@dataclass(frozen=True, eq=False)
class Kernel:
    """A discrete blur kernel: B(p) = Σ_u k(u) S(p − u) with k(u) = weights[oy + u_y, ox + u_x].

    Attributes
    ----------
    weights : float32 [kh, kw], sums to 1.
    origin : (oy, ox), the array index of zero displacement.
    coverage : fraction of the window's weight (5τ, or the exposure) covered by gyro samples;
        < 1 means the rate was held constant beyond the first/last sample.
    n_samples : gyro samples inside the window.
    """

    weights: np.ndarray
    origin: tuple[int, int]
    coverage: float = 1.0
    n_samples: int = 0

    def __post_init__(self):
        w = self.weights
        if not isinstance(w, np.ndarray) or w.dtype != np.float32:
            w = np.asarray(w, dtype=np.float32)
            object.__setattr__(self, "weights", w)
        if w.ndim != 2 or w.size == 0:
            raise KernelError(f"Kernel.weights: expected a non-empty 2-D array, got shape {w.shape}")
        try:
            oy, ox = (int(o) for o in self.origin)
        except (TypeError, ValueError):
            raise KernelError(f"Kernel.origin: expected (oy, ox) integers, got {self.origin!r}") from None
        if not (0 <= oy < w.shape[0] and 0 <= ox < w.shape[1]):
            raise KernelError(f"Kernel.origin: {self.origin!r} lies outside weights of shape {w.shape}")
        object.__setattr__(self, "origin", (oy, ox))

    @functools.cached_property
    def extent_px(self) -> float:
        """max |u| over the non-zero weights (px)."""
        iy, ix = np.nonzero(self.weights)
        if iy.size == 0:
            return 0.0
        return float(np.sqrt(((iy - self.origin[0]) ** 2 + (ix - self.origin[1]) ** 2).max()))

    @functools.cached_property
    def centroid(self) -> tuple[float, float]:
        """Mean displacement (u_y, u_x) = Σ_u k(u) u (px)."""
        w = self.weights.astype(np.float64)
        iy, ix = np.indices(w.shape)
        s = w.sum()
        return (float((w * (iy - self.origin[0])).sum() / s), float((w * (ix - self.origin[1])).sum() / s))

    @property
    def shape(self) -> tuple[int, int]:
        return self.weights.shape


@dataclass(frozen=True, eq=False)
class KernelPath:
    """The sampled image path of one pixel before splatting: node times, offsets and weights.

    `t` (camera clock, s), `u` float64 [n, 2] offsets (u_x, u_y) in px, `w` float64 [n] normalised
    quadrature weights (sum 1). Splatting `w` at `u` bilinearly gives the kernel without PSF.
    """

    t: np.ndarray
    u: np.ndarray
    w: np.ndarray
    coverage: float
    n_samples: int


@dataclass(frozen=True, eq=False)
class KernelGrid:
    """One kernel per cell of a rows × cols grid over the image (spatially varying blur).

    `kernels[r][c]` is rendered at the cell centre `centers[r, c] = (y, x)`; `bounds[r, c]` =
    (y0, y1, x0, x1), half-open pixel bounds of the cell; `times[r]` is the read time used for the
    cells of row r (rolling readout); `image_shape` = (H, W).
    """

    kernels: list
    centers: np.ndarray
    bounds: np.ndarray
    times: np.ndarray
    image_shape: tuple[int, int]
    kind: str = "thermal"

    @property
    def grid(self) -> tuple[int, int]:
        return self.centers.shape[0], self.centers.shape[1]

    @property
    def coverage(self) -> float:
        return min(k.coverage for row in self.kernels for k in row)

    @property
    def max_extent_px(self) -> float:
        return max(k.extent_px for row in self.kernels for k in row)

    def kernel_at(self, y: float, x: float) -> Kernel:
        """The kernel of the cell containing pixel (y, x)."""
        r = int(np.clip(np.searchsorted(self.bounds[:, 0, 1], y, side="right"), 0, self.grid[0] - 1))
        c = int(np.clip(np.searchsorted(self.bounds[0, :, 3], x, side="right"), 0, self.grid[1] - 1))
        return self.kernels[r][c]


# ---------------------------------------------------------------------------- calibration params
@dataclass(frozen=True)
class _Params:
    M: np.ndarray        # ω_cam = M (ω_gyro − bias)
    bias: np.ndarray
    offset: float
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    tau: float
    readout: float
    psf_sigma: float


def _make_params(calib: Calibration) -> _Params:
    if not isinstance(calib, Calibration):
        raise KernelError(f"calib: expected a Calibration, got {type(calib).__name__}")
    M = np.ascontiguousarray(calib.gyro_to_camera_matrix, dtype=np.float64)
    bias = np.ascontiguousarray(np.asarray(calib.bias_rad_s, dtype=np.float64).ravel())
    if M.shape != (3, 3) or not np.isfinite(M).all():
        raise KernelError(f"calib.R_cam_gyro/scale: expected a finite 3×3 gyro→camera map, got {M}")
    if bias.shape != (3,) or not np.isfinite(bias).all():
        raise KernelError(f"calib.bias_rad_s: expected 3 finite values, got {calib.bias_rad_s!r}")
    for name in ("fx", "fy", "tau_s", "width", "height"):
        v = float(getattr(calib, name))
        if not (math.isfinite(v) and v > 0):
            raise KernelError(f"calib.{name}: expected a finite positive value, got {v!r}")
    for name in ("cx", "cy", "time_offset_s", "readout_s"):
        v = float(getattr(calib, name))
        if not math.isfinite(v) or (name == "readout_s" and v < 0):
            raise KernelError(f"calib.{name}: expected a finite value (≥ 0 for readout_s), got {v!r}")
    sigma = float(calib.psf_sigma_px)
    if not (math.isfinite(sigma) and sigma >= 0):
        raise KernelError(f"calib: optical PSF σ (Eq. 19) must be finite and ≥ 0, got {sigma!r} px "
                          "(check wavelength_um, f_number, psf_beta, pixel_pitch_um)")
    return _Params(M, bias, float(calib.time_offset_s), float(calib.fx), float(calib.fy),
                   float(calib.cx), float(calib.cy), int(calib.width), int(calib.height),
                   float(calib.tau_s), float(calib.readout_s), sigma)


@functools.lru_cache(maxsize=64)
def _params_cached(calib: Calibration) -> _Params:
    return _make_params(calib)


def _params(calib: Calibration) -> _Params:
    try:
        return _params_cached(calib)
    except TypeError:   # unhashable fields (e.g. numpy arrays passed directly): no caching
        return _make_params(calib)


def row_time(calib: Calibration, t_frame: float, row: float) -> float:
    """Read time of image row `row` under rolling readout: t_frame − readout_s·(1 − (row+1)/H)."""
    return float(t_frame) - float(calib.readout_s) * (1.0 - (float(row) + 1.0) / float(calib.height))


# ------------------------------------------------------------------------------------- validation
def _check_gyro(gyro_t, gyro_rate) -> tuple[np.ndarray, np.ndarray]:
    """Shapes and dtypes (cheap); finiteness and ordering are checked on the window's samples only."""
    t = np.asarray(gyro_t)
    r = np.asarray(gyro_rate)
    if t.ndim != 1:
        raise KernelError(f"gyro_t: expected a 1-D array of sample times, got shape {t.shape}")
    if r.ndim != 2 or r.shape[1] != 3:
        raise KernelError(f"gyro_rate: expected shape [n, 3] (rad/s, gyro frame), got {r.shape}")
    if r.shape[0] != t.shape[0]:
        raise KernelError(f"gyro_rate: has {r.shape[0]} samples but gyro_t has {t.shape[0]}")
    if t.shape[0] == 0:
        raise KernelError("gyro_t: no gyro samples; a kernel needs at least one")
    if t.dtype != np.float64:
        if not (np.issubdtype(t.dtype, np.floating) or np.issubdtype(t.dtype, np.integer)):
            raise KernelError(f"gyro_t: expected float seconds, got dtype {t.dtype}")
        t = t.astype(np.float64)
    if r.dtype != np.float32 and r.dtype != np.float64:
        if not (np.issubdtype(r.dtype, np.floating) or np.issubdtype(r.dtype, np.integer)):
            raise KernelError(f"gyro_rate: expected float rad/s, got dtype {r.dtype}")
        r = r.astype(np.float64)
    return t, r


def _check_scalar(name: str, v, positive: bool = False) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise KernelError(f"{name}: expected a number, got {v!r}") from None
    if not math.isfinite(f) or (positive and f <= 0):
        raise KernelError(f"{name}: expected a finite{' positive' if positive else ''} number, got {v!r}")
    return f


def _check_point(point, p: _Params) -> tuple[float, float]:
    if point is None:
        return p.cx, p.cy
    try:
        x, y = (float(c) for c in point)
    except (TypeError, ValueError):
        raise KernelError(f"point: expected (x, y) pixel coordinates, got {point!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise KernelError(f"point: expected finite (x, y), got {point!r}")
    return x, y


def _window_slice(t: np.ndarray, r: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """The samples covering [lo, hi] (gyro clock) plus one neighbour each side, validated."""
    n = t.shape[0]
    i0 = max(int(np.searchsorted(t, lo, side="right")) - 1, 0)
    i1 = min(int(np.searchsorted(t, hi, side="left")) + 1, n)
    if i1 <= i0:   # all samples on one side: keep the nearest one (its rate is held)
        i0, i1 = (n - 1, n) if i0 >= n - 1 else (0, 1)
    ts = np.ascontiguousarray(t[i0:i1], dtype=np.float64)
    rs = np.ascontiguousarray(r[i0:i1], dtype=np.float64)
    if not np.isfinite(ts).all():
        raise KernelError(f"gyro_t: non-finite sample times near the window [{lo:.6f}, {hi:.6f}] s")
    if ts.shape[0] > 1 and not (np.diff(ts) > 0).all():
        raise KernelError(f"gyro_t: sample times must be strictly increasing (near {lo:.6f}..{hi:.6f} s)")
    if not np.isfinite(rs).all():
        raise KernelError(f"gyro_rate: NaN/inf rates in the window [{lo:.6f}, {hi:.6f}] s (gyro clock)")
    return ts, rs


# ------------------------------------------------------------------------------------- numba core
@njit(cache=True, nogil=True)
def _rate_at(t, w, s, out):
    """ω(s): linear between samples, held constant outside them (into out[3])."""
    n = t.shape[0]
    if s <= t[0]:
        for a in range(3):
            out[a] = w[0, a]
        return
    if s >= t[n - 1]:
        for a in range(3):
            out[a] = w[n - 1, a]
        return
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if t[mid] <= s:
            lo = mid
        else:
            hi = mid
    f = (s - t[lo]) / (t[hi] - t[lo])
    for a in range(3):
        out[a] = w[lo, a] + f * (w[hi, a] - w[lo, a])


@njit(cache=True, nogil=True)
def _so3_exp_into(px, py, pz, out):
    """Rodrigues exp([φ]×) into out[3, 3] (series near 0, as thermod.physics.geometry.so3_exp)."""
    th2 = px * px + py * py + pz * pz
    th = math.sqrt(th2)
    if th < 1e-8:
        a = 1.0
        b = 0.5
    else:
        a = math.sin(th) / th
        sh = math.sin(0.5 * th)
        b = 2.0 * sh * sh / th2   # = (1 − cos θ)/θ² without the cancellation at small θ
    out[0, 0] = 1.0 + b * (-py * py - pz * pz)
    out[0, 1] = -a * pz + b * px * py
    out[0, 2] = a * py + b * px * pz
    out[1, 0] = a * pz + b * px * py
    out[1, 1] = 1.0 + b * (-px * px - pz * pz)
    out[1, 2] = -a * px + b * py * pz
    out[2, 0] = -a * py + b * px * pz
    out[2, 1] = a * px + b * py * pz
    out[2, 2] = 1.0 + b * (-px * px - py * py)


@njit(cache=True, nogil=True)
def _hat_weights(x, y, b, tau, uniform):
    """∫ over [x, y] of the window weight times the hats (1−λ, λ), λ = (s−x)/(y−x).

    Exponential: e(s) = exp(−(b − s)/τ) (Eq. 18, continuous form); uniform: e = 1 (Eq. 17).
    """
    h = y - x
    if uniform:
        return 0.5 * h, 0.5 * h
    r = h / tau
    ex = math.exp(-(b - x) / tau)
    if r < 1e-4:   # series of 1 + g − g/r, g = expm1(r): avoids cancellation
        right = tau * ex * (0.5 * r + r * r / 3.0 + r * r * r / 8.0)
    else:
        g = math.expm1(r)
        right = tau * ex * (1.0 + g - g / r)
    total = tau * ex * math.expm1(r)
    return total - right, right


@njit(cache=True, nogil=True)
def _path_nodes(t_all, r_all, offset, M, bias, a, b, tau, uniform, px_per_rad, max_step, max_nodes):
    """Rotations Q(s) = R(b)ᵀR(s) and normalised quadrature weights at sub-nodes of (a, b].

    Reads only the samples around the window (a whole ring may be passed). The rate is calibrated
    here (ω_cam = M (ω_gyro − bias), at t + offset), piecewise linear between samples and held
    outside them. Each stretch between consecutive samples is split into enough sub-steps that the
    image moves ≤ max_step px per step (bound: px_per_rad · |ω| · Δs). Every sub-node's Q is taken
    directly from its stretch's end node, Q(s) = Q(s1) exp(−½(ω(s)+ω(s1))(s1−s)), so at the sample
    times it equals `integrate_rotations` exactly.
    Returns (times, Q, w, coverage, n_samples, status); status: 0 ok, 1 too many nodes,
    4 non-finite times, 5 times not increasing, 6 non-finite rates.
    """
    m_all = t_all.shape[0]
    i0 = np.searchsorted(t_all, a - offset, side="right") - 1
    i1 = np.searchsorted(t_all, b - offset, side="left") + 1
    if i0 < 0:
        i0 = 0
    if i1 > m_all:
        i1 = m_all
    if i1 <= i0:   # all samples on one side of the window: keep the nearest one (its rate is held)
        if i0 >= m_all - 1:
            i0 = m_all - 1
            i1 = m_all
        else:
            i0 = 0
            i1 = 1
    n = i1 - i0
    t = np.empty(n)
    w = np.empty((n, 3))
    for i in range(n):
        ti = t_all[i0 + i]
        if not math.isfinite(ti):
            return np.empty(0), np.empty((0, 3, 3)), np.empty(0), 0.0, 0, 4
        if i > 0 and not ti > t_all[i0 + i - 1]:
            return np.empty(0), np.empty((0, 3, 3)), np.empty(0), 0.0, 0, 5
        t[i] = ti + offset
        d0 = r_all[i0 + i, 0] - bias[0]
        d1 = r_all[i0 + i, 1] - bias[1]
        d2 = r_all[i0 + i, 2] - bias[2]
        if not (math.isfinite(d0) and math.isfinite(d1) and math.isfinite(d2)):
            return np.empty(0), np.empty((0, 3, 3)), np.empty(0), 0.0, 0, 6
        for r in range(3):
            w[i, r] = M[r, 0] * d0 + M[r, 1] * d1 + M[r, 2] * d2
    # stretch boundaries: a, samples strictly inside (a, b), b
    n_in = 0
    n_samples = 0
    for i in range(n):
        if t[i] > a and t[i] < b:
            n_in += 1
        if t[i] > a and t[i] <= b:
            n_samples += 1
    nb = n_in + 2
    bt = np.empty(nb)
    bw = np.empty((nb, 3))
    tmp = np.empty(3)
    bt[0] = a
    _rate_at(t, w, a, tmp)
    bw[0, :] = tmp
    j = 1
    for i in range(n):
        if t[i] > a and t[i] < b:
            bt[j] = t[i]
            bw[j, :] = w[i, :]
            j += 1
    bt[nb - 1] = b
    _rate_at(t, w, b, tmp)
    bw[nb - 1, :] = tmp
    # sub-step counts
    nsub = np.empty(nb - 1, dtype=np.int64)
    total = 1
    for k in range(nb - 1):
        m0 = math.sqrt(bw[k, 0] ** 2 + bw[k, 1] ** 2 + bw[k, 2] ** 2)
        m1 = math.sqrt(bw[k + 1, 0] ** 2 + bw[k + 1, 1] ** 2 + bw[k + 1, 2] ** 2)
        move = px_per_rad * max(m0, m1) * (bt[k + 1] - bt[k])
        c = int(math.ceil(move / max_step))
        if c < 1:
            c = 1
        nsub[k] = c
        total += c
        if total > max_nodes:
            return np.empty(0), np.empty((0, 3, 3)), np.empty(0), 0.0, n_samples, 1
    times = np.empty(total)
    Q = np.empty((total, 3, 3))
    wt = np.zeros(total)
    E = np.empty((3, 3))
    idx = total - 1
    times[idx] = b
    for r in range(3):
        for c in range(3):
            Q[idx, r, c] = 1.0 if r == c else 0.0
    for k in range(nb - 2, -1, -1):
        s0 = bt[k]
        s1 = bt[k + 1]
        end = idx   # node at s1
        for jj in range(nsub[k] - 1, -1, -1):
            s = s0 + (s1 - s0) * jj / nsub[k]
            f = (s - s0) / (s1 - s0)
            dt = s1 - s
            px = -0.5 * (bw[k, 0] + f * (bw[k + 1, 0] - bw[k, 0]) + bw[k + 1, 0]) * dt
            py = -0.5 * (bw[k, 1] + f * (bw[k + 1, 1] - bw[k, 1]) + bw[k + 1, 1]) * dt
            pz = -0.5 * (bw[k, 2] + f * (bw[k + 1, 2] - bw[k, 2]) + bw[k + 1, 2]) * dt
            _so3_exp_into(px, py, pz, E)
            idx -= 1
            times[idx] = s
            for r in range(3):
                for c in range(3):
                    Q[idx, r, c] = Q[end, r, 0] * E[0, c] + Q[end, r, 1] * E[1, c] + Q[end, r, 2] * E[2, c]
    # quadrature weights (hat functions over each sub-interval), normalised
    acc = 0.0
    for i in range(total - 1):
        wl, wr = _hat_weights(times[i], times[i + 1], b, tau, uniform)
        wt[i] += wl
        wt[i + 1] += wr
        acc += wl + wr
    for i in range(total):
        wt[i] /= acc
    # coverage: share of the window weight inside [first sample, last sample]
    lo = max(a, t[0])
    hi = min(b, t[n - 1])
    if hi <= lo:
        cov = 0.0
    elif uniform:
        cov = (hi - lo) / (b - a)
    else:
        cov = (math.exp(-(b - hi) / tau) - math.exp(-(b - lo) / tau)) / (1.0 - math.exp(-(b - a) / tau))
    return times, Q, wt, min(cov, 1.0), n_samples, 0


@njit(cache=True, nogil=True)
def _offsets(Q, px, py, fx, fy, cx, cy):
    """u_i = p − π(K Q_i K⁻¹ p) (Eq. 16) as [n, 2] (u_x, u_y); status 1 if a ray leaves the view."""
    n = Q.shape[0]
    u = np.empty((n, 2))
    dx = (px - cx) / fx
    dy = (py - cy) / fy
    for i in range(n):
        q0 = Q[i, 0, 0] * dx + Q[i, 0, 1] * dy + Q[i, 0, 2]
        q1 = Q[i, 1, 0] * dx + Q[i, 1, 1] * dy + Q[i, 1, 2]
        q2 = Q[i, 2, 0] * dx + Q[i, 2, 1] * dy + Q[i, 2, 2]
        if q2 <= 1e-6:
            return u, 1
        u[i, 0] = px - (fx * q0 / q2 + cx)
        u[i, 1] = py - (fy * q1 / q2 + cy)
    return u, 0


@njit(cache=True, nogil=True)
def _cell(v):
    """(integer cell, fraction) of a coordinate, snapped so that exact integers give a single cell,
    not a zero-weight neighbour."""
    fl = math.floor(v)
    f = v - fl
    if f > 1.0 - 1e-9:
        return int(fl) + 1, 0.0
    if f < 1e-9:
        return int(fl), 0.0
    return int(fl), f


@njit(cache=True, nogil=True)
def _splat(u, w, max_size):
    """Bilinear splat of weights w at offsets u into a tight float64 array; returns (k, oy, ox, status)."""
    n = u.shape[0]
    ix = np.empty(n, dtype=np.int64)
    iy = np.empty(n, dtype=np.int64)
    fxs = np.empty(n)
    fys = np.empty(n)
    xmin = 1 << 40
    ymin = 1 << 40
    xmax = -(1 << 40)
    ymax = -(1 << 40)
    for i in range(n):
        ix[i], fxs[i] = _cell(u[i, 0])
        iy[i], fys[i] = _cell(u[i, 1])
        if w[i] == 0.0:
            continue
        xmin = min(xmin, ix[i])
        ymin = min(ymin, iy[i])
        xmax = max(xmax, ix[i] + (1 if fxs[i] > 0.0 else 0))
        ymax = max(ymax, iy[i] + (1 if fys[i] > 0.0 else 0))
    if xmax < xmin:
        xmin = 0
        xmax = 0
        ymin = 0
        ymax = 0
    kw = xmax - xmin + 1
    kh = ymax - ymin + 1
    if kw > max_size or kh > max_size:
        return np.zeros((1, 1)), 0, 0, 1
    k = np.zeros((kh, kw))
    acc = 0.0
    for i in range(n):
        if w[i] == 0.0:
            continue
        x = ix[i] - xmin
        y = iy[i] - ymin
        fx = fxs[i]
        fy = fys[i]
        k[y, x] += w[i] * (1.0 - fx) * (1.0 - fy)
        if fx > 0.0:
            k[y, x + 1] += w[i] * fx * (1.0 - fy)
        if fy > 0.0:
            k[y + 1, x] += w[i] * (1.0 - fx) * fy
            if fx > 0.0:
                k[y + 1, x + 1] += w[i] * fx * fy
        acc += w[i]
    if acc > 0.0:
        for y in range(kh):
            for x in range(kw):
                k[y, x] /= acc
    return k, -ymin, -xmin, 0


@njit(cache=True, nogil=True)
def _convolve_sep(k, g):
    """Full 2-D convolution of k with the separable symmetric kernel g ⊗ g (grows by len(g)//2 a side)."""
    kh, kw = k.shape
    r = g.shape[0] // 2
    tmp = np.zeros((kh, kw + 2 * r))
    for y in range(kh):
        for x in range(kw):
            v = k[y, x]
            if v == 0.0:
                continue
            for j in range(g.shape[0]):
                tmp[y, x + j] += v * g[j]
    out = np.zeros((kh + 2 * r, kw + 2 * r), dtype=np.float32)
    for y in range(kh):
        for x in range(kw + 2 * r):
            v = tmp[y, x]
            if v == 0.0:
                continue
            for j in range(g.shape[0]):
                out[y + j, x] += np.float32(v * g[j])
    return out


@njit(cache=True, nogil=True)
def _kernel_at(Q, w, px, py, fx, fy, cx, cy, max_size, g):
    """Offsets at pixel (px, py), bilinear splat, PSF (g: 1-D taps; length 1 = none) → float32 kernel.

    Returns (weights, oy, ox, status); status 2 = a ray turned behind the camera, 3 = too large.
    """
    u, st = _offsets(Q, px, py, fx, fy, cx, cy)
    if st:
        return np.zeros((1, 1), dtype=np.float32), 0, 0, 2
    k, oy, ox, st = _splat(u, w, max_size)
    if st:
        return np.zeros((1, 1), dtype=np.float32), 0, 0, 3
    r = g.shape[0] // 2
    if r == 0:
        return k.astype(np.float32), oy, ox, 0
    return _convolve_sep(k, g), oy + r, ox + r, 0


@njit(cache=True, nogil=True)
def _render_one(t_all, r_all, offset, M, bias, a, b, tau, uniform, px_per_rad, max_step, max_nodes,
                px, py, fx, fy, cx, cy, max_size, g):
    """`_path_nodes` then `_kernel_at` in one call (one dispatch per kernel)."""
    times, Q, w, cov, ns, st = _path_nodes(t_all, r_all, offset, M, bias, a, b, tau, uniform, px_per_rad,
                                           max_step, max_nodes)
    if st:
        return np.zeros((1, 1), dtype=np.float32), 0, 0, cov, ns, st
    k, oy, ox, st = _kernel_at(Q, w, px, py, fx, fy, cx, cy, max_size, g)
    return k, oy, ox, cov, ns, st


# ------------------------------------------------------------------------------------ public API
@functools.lru_cache(maxsize=32)
def _gauss_1d(sigma: float) -> np.ndarray:
    """Sampled, normalised Gaussian, radius ceil(3σ) (as cv2.getGaussianKernel samples it)."""
    if sigma <= 0:
        return _NO_PSF
    r = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    g.setflags(write=False)
    return g


def optical_psf(sigma_px: float) -> Kernel:
    """Optical PSF (Eq. 19) as a kernel: a sampled Gaussian of σ = sigma_px, radius ceil(3σ).

    σ = 0 gives a delta. `Calibration.psf_sigma_px` = 0.45·λ·F#/β / pitch.
    """
    s = _check_scalar("sigma_px", sigma_px)
    if s < 0:
        raise KernelError(f"sigma_px: expected ≥ 0, got {sigma_px!r}")
    g = _gauss_1d(s)
    w = np.outer(g, g).astype(np.float32)
    r = g.shape[0] // 2
    return Kernel(w, (r, r), 1.0, 0)


def _max_size(p: _Params) -> int:
    # A blur wider than twice the frame cannot be a real motion; refuse rather than crop.
    return 2 * max(p.width, p.height) + 64


def _px_per_rad(p: _Params, x: float, y: float) -> float:
    """Upper bound on image speed per rad/s (px) at (x, y) and at the image corners: f·(1 + ρ²).

    The rotational motion field at normalised (x, y) is bounded by |ω|·(1 + x² + y²); the bound is
    taken over the whole frame (so every point of a frame gets the same sub-steps and a grid cell's
    kernel equals the single kernel rendered there), with a margin for rays drifting outward.
    """
    rx = max(abs(p.cx + 0.5), abs(p.width - 0.5 - p.cx), abs(x - p.cx)) / p.fx
    ry = max(abs(p.cy + 0.5), abs(p.height - 0.5 - p.cy), abs(y - p.cy)) / p.fy
    rho = math.sqrt(rx * rx + ry * ry) + 0.05
    return max(p.fx, p.fy) * (1.0 + rho * rho) * 1.05


_STATUS = {
    1: "the motion needs more than {n} path nodes (rates of thousands of rad/s?): check the gyro units/scale",
    2: "the camera turned more than 90° within the window: check the gyro units (rad/s) and scale",
    3: "the blur path spans more than {size} px: check the gyro units (rad/s) and scale",
    4: "gyro_t: non-finite sample times in the window",
    5: "gyro_t: sample times must be strictly increasing",
    6: "gyro_rate: NaN/inf rates in the window",
}


def _raise_status(st: int, p: _Params, a: float, b: float, x: float, y: float):
    msg = _STATUS[int(st)].format(n=MAX_NODES, size=_max_size(p))
    if not msg.startswith("gyro_"):
        msg = f"gyro_rate: at point ({x:.1f}, {y:.1f}), {msg}"
    raise KernelError(f"{msg} (window [{a:.6f}, {b:.6f}] s, camera clock)")


_NO_PSF = np.ones(1)
_NO_PSF.setflags(write=False)   # read-only like the cached Gaussians: one numba specialisation


def _psf_taps(p: _Params, psf: bool) -> np.ndarray:
    return _gauss_1d(p.psf_sigma) if psf and p.psf_sigma > 0 else _NO_PSF


def _nodes_for(t, r, p: _Params, a: float, b: float, uniform: bool, ppr: float, x: float, y: float):
    tau = p.tau if not uniform else 1.0
    times, Q, w, cov, ns, st = _path_nodes(t, r, p.offset, p.M, p.bias, a, b, tau, uniform, ppr,
                                           MAX_STEP_PX, MAX_NODES)
    if st:
        _raise_status(st, p, a, b, x, y)
    return times, Q, w, float(cov), int(ns)


def _kernel_from_nodes(Q, w, cov, n_samples, p: _Params, x: float, y: float, psf: bool, a, b) -> Kernel:
    k, oy, ox, st = _kernel_at(Q, w, x, y, p.fx, p.fy, p.cx, p.cy, _max_size(p), _psf_taps(p, psf))
    if st:
        _raise_status(st, p, a, b, x, y)
    return Kernel(k, (int(oy), int(ox)), cov, n_samples)


def _render(t, r, p: _Params, a: float, b: float, uniform: bool, x: float, y: float, psf: bool) -> Kernel:
    k, oy, ox, cov, ns, st = _render_one(t, r, p.offset, p.M, p.bias, a, b, p.tau if not uniform else 1.0,
                                         uniform, _px_per_rad(p, x, y), MAX_STEP_PX, MAX_NODES,
                                         x, y, p.fx, p.fy, p.cx, p.cy, _max_size(p), _psf_taps(p, psf))
    if st:
        _raise_status(st, p, a, b, x, y)
    return Kernel(k, (int(oy), int(ox)), float(cov), int(ns))


def _window(calib_p: _Params, t_frame, y: float, length: float) -> tuple[float, float]:
    b = float(t_frame) - calib_p.readout * (1.0 - (y + 1.0) / calib_p.height)
    return b - length, b


def render_path(gyro_t, gyro_rate, calib: Calibration, t_frame: float, *, point=None, m: float = 5.0,
                exposure_s: float | None = None) -> KernelPath:
    """The sampled image path behind a kernel (before splatting and PSF), for plots and fits.

    Thermal weights over (t − mτ, t] by default; box weights over (t − exposure_s, t] when
    `exposure_s` is given. `t` is the read time of the point's row (rolling readout).
    """
    t, r = _check_gyro(gyro_t, gyro_rate)
    p = _params(calib)
    tf = _check_scalar("t_frame", t_frame)
    x, y = _check_point(point, p)
    uniform = exposure_s is not None
    length = _check_scalar("exposure_s", exposure_s, True) if uniform else _check_scalar("m", m, True) * p.tau
    a, b = _window(p, tf, y, length)
    times, Q, w, cov, ns = _nodes_for(t, r, p, a, b, uniform, _px_per_rad(p, x, y), x, y)
    u, st = _offsets(Q, x, y, p.fx, p.fy, p.cx, p.cy)
    if st:
        _raise_status(2, p, a, b, x, y)
    return KernelPath(times, u, w, cov, ns)


def render_thermal_kernel(gyro_t, gyro_rate, calib: Calibration, t_frame: float, *, point=None,
                          m: float = 5.0, psf: bool = True) -> Kernel:
    """Microbolometer blur kernel (Eq. 18) of the frame read at `t_frame`, at pixel `point`.

    Parameters
    ----------
    gyro_t, gyro_rate : RAW gyro samples, float [n] s (gyro clock) and [n, 3] rad/s (gyro frame);
        `calib` maps them to the camera (bias, scale, R_cam_gyro, time offset). Only the samples
        around the window are read, so a whole ring buffer may be passed.
    calib : Calibration (intrinsics, τ, optics, readout, gyro→camera).
    t_frame : frame time (s, camera clock): when its last row was read.
    point : (x, y) pixel; default the principal point. Under rolling readout the window ends at the
        read time of row y: t_frame − readout_s·(1 − (y+1)/H).
    m : window length in τ: (t − mτ, t]; m = 5 leaves 0.7 % of the weight out.
    psf : convolve with the optical PSF (Eq. 19, σ = calib.psf_sigma_px).

    Returns
    -------
    Kernel with weights ∝ ∫ exp(−(t − s)/τ) δ(u − u(s)) ds, normalised to 1; `coverage` < 1 when
    the gyro does not span the window (the rate is then held at the first/last sample).
    """
    t, r = _check_gyro(gyro_t, gyro_rate)
    p = _params(calib)
    tf = _check_scalar("t_frame", t_frame)
    mm = _check_scalar("m", m, True)
    x, y = _check_point(point, p)
    a, b = _window(p, tf, y, mm * p.tau)
    return _render(t, r, p, a, b, False, x, y, psf)


def render_photon_kernel(gyro_t, gyro_rate, calib: Calibration, t_frame: float, exposure_s: float, *,
                         point=None, psf: bool = True) -> Kernel:
    """Photon-detector (CCD/CMOS) blur kernel (Eq. 17): equal weights over (t − exposure_s, t].

    The baseline the thermal kernel must beat on a microbolometer; same path machinery, same
    arguments as `render_thermal_kernel`.
    """
    t, r = _check_gyro(gyro_t, gyro_rate)
    p = _params(calib)
    tf = _check_scalar("t_frame", t_frame)
    ex = _check_scalar("exposure_s", exposure_s, True)
    x, y = _check_point(point, p)
    a, b = _window(p, tf, y, ex)
    return _render(t, r, p, a, b, True, x, y, psf)


def _grid_layout(h: int, w: int, rows: int, cols: int):
    ye = np.round(np.linspace(0, h, rows + 1)).astype(int)
    xe = np.round(np.linspace(0, w, cols + 1)).astype(int)
    centers = np.empty((rows, cols, 2))
    bounds = np.empty((rows, cols, 4), dtype=np.int64)
    for i in range(rows):
        for j in range(cols):
            centers[i, j] = ((ye[i] + ye[i + 1] - 1) / 2.0, (xe[j] + xe[j + 1] - 1) / 2.0)
            bounds[i, j] = (ye[i], ye[i + 1], xe[j], xe[j + 1])
    return centers, bounds


def render_kernel_grid(gyro_t, gyro_rate, calib: Calibration, t_frame: float, grid=(6, 8), *,
                       kind: str = "thermal", psf: bool = True, m: float = 5.0,
                       exposure_s: float | None = None) -> KernelGrid:
    """One kernel per cell centre of a rows × cols grid (roll makes the blur vary over the image).

    Under rolling readout the cells of a grid row centred on image row y use the read time
    t_frame − readout_s·(1 − (y+1)/H). `kind` = "thermal" (Eq. 18, window mτ) or "photon"
    (Eq. 17, `exposure_s`, default one frame period 1/frame_rate_hz). The rotations are integrated
    once per grid row and shared by its cells.
    """
    t, r = _check_gyro(gyro_t, gyro_rate)
    p = _params(calib)
    tf = _check_scalar("t_frame", t_frame)
    try:
        rows, cols = (int(g) for g in grid)
    except (TypeError, ValueError):
        raise KernelError(f"grid: expected (rows, cols), got {grid!r}") from None
    if rows < 1 or cols < 1 or rows > p.height or cols > p.width:
        raise KernelError(f"grid: expected 1 ≤ rows ≤ {p.height} and 1 ≤ cols ≤ {p.width}, got {grid!r}")
    if kind == "thermal":
        uniform, length = False, _check_scalar("m", m, True) * p.tau
    elif kind == "photon":
        uniform = True
        length = _check_scalar("exposure_s", exposure_s if exposure_s is not None
                               else 1.0 / float(calib.frame_rate_hz), True)
    else:
        raise KernelError(f"kind: expected 'thermal' or 'photon', got {kind!r}")
    centers, bounds = _grid_layout(p.height, p.width, rows, cols)
    ppr = _px_per_rad(p, p.cx, p.cy)   # the frame-wide bound: same sub-steps as single kernels
    kernels = []
    times = np.empty(rows)
    for i in range(rows):
        y = float(centers[i, 0, 0])
        a, b = _window(p, tf, y, length)
        times[i] = b
        _, Q, w, cov, ns = _nodes_for(t, r, p, a, b, uniform, ppr, p.cx, y)
        kernels.append([_kernel_from_nodes(Q, w, cov, ns, p, float(centers[i, j, 1]), y, psf, a, b)
                        for j in range(cols)])
    return KernelGrid(kernels, centers, bounds, times, (p.height, p.width), kind)


# --------------------------------------------------------------------------------- forward model
def _as_image(image, name="image") -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 2 or img.shape[0] == 0 or img.shape[1] == 0:
        raise KernelError(f"{name}: expected a non-empty 2-D array [H, W], got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.floating) or np.issubdtype(img.dtype, np.integer)):
        raise KernelError(f"{name}: expected a numeric image, got dtype {img.dtype}")
    return np.ascontiguousarray(img, dtype=np.float32)


def _check_kernel(kernel) -> Kernel:
    if not isinstance(kernel, Kernel):
        raise KernelError(f"kernel: expected a thermod.physics.kernels.Kernel, got {type(kernel).__name__}")
    return kernel   # shape and origin were checked when it was made


def _filter(img: np.ndarray, kernel: Kernel, border: int) -> np.ndarray:
    w = kernel.weights
    kh, kw = w.shape
    oy, ox = kernel.origin
    flipped = np.ascontiguousarray(w[::-1, ::-1], dtype=np.float32)
    # correlation with the flipped kernel anchored at (kw−1−ox, kh−1−oy) is B(p) = Σ_u k(u) S(p − u)
    return cv2.filter2D(img, cv2.CV_32F, flipped, anchor=(kw - 1 - ox, kh - 1 - oy), borderType=border)


def blur(image, kernel: Kernel) -> np.ndarray:
    """The forward model B(p) = Σ_u k(u) S(p − u) (float32 out, replicate border)."""
    img = _as_image(image)
    return _filter(img, _check_kernel(kernel), cv2.BORDER_REPLICATE)


def _tents(centers: np.ndarray, n: int) -> np.ndarray:
    """Partition-of-unity hat weights [len(centers), n] along one axis, flat beyond the end centres."""
    x = np.arange(n, dtype=np.float64)
    k = len(centers)
    out = np.zeros((k, n))
    if k == 1:
        out[0] = 1.0
        return out
    for i, c in enumerate(centers):
        if i > 0:
            lo = centers[i - 1]
            sel = (x >= lo) & (x <= c)
            out[i, sel] = (x[sel] - lo) / (c - lo)
        else:
            out[i, x <= c] = 1.0
        if i < k - 1:
            hi = centers[i + 1]
            sel = (x > c) & (x < hi)
            out[i, sel] = (hi - x[sel]) / (hi - c)
        else:
            out[i, x > c] = 1.0
    return out


def blur_varying(image, grid: KernelGrid) -> np.ndarray:
    """Spatially varying forward model: per-cell blurs blended with bilinear (tent) weights.

    Between cell centres the weights fall linearly from one cell to the next (a partition of
    unity), so the blur changes smoothly; a uniform grid reproduces `blur` exactly.
    """
    img = _as_image(image)
    if not isinstance(grid, KernelGrid):
        raise KernelError(f"grid: expected a thermod.physics.kernels.KernelGrid, got {type(grid).__name__}")
    h, w = img.shape
    if tuple(grid.image_shape) != (h, w):
        raise KernelError(f"grid: rendered for images of shape {tuple(grid.image_shape)}, image is {(h, w)}")
    rows, cols = grid.grid
    for row in grid.kernels:
        for k in row:
            _check_kernel(k)
    pad = max(max(k.weights.shape) for row in grid.kernels for k in row)
    padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    ty = _tents(grid.centers[:, 0, 0], h)
    tx = _tents(grid.centers[0, :, 1], w)
    out = np.zeros((h, w), dtype=np.float32)
    for i in range(rows):
        ys = np.nonzero(ty[i])[0]
        y0, y1 = int(ys[0]), int(ys[-1]) + 1
        for j in range(cols):
            xs = np.nonzero(tx[j])[0]
            x0, x1 = int(xs[0]), int(xs[-1]) + 1
            crop = padded[y0:y1 + 2 * pad, x0:x1 + 2 * pad]
            # the crop extends `pad` beyond the region, so its own border never reaches the result
            b = _filter(crop, grid.kernels[i][j], cv2.BORDER_REPLICATE)[pad:pad + y1 - y0, pad:pad + x1 - x0]
            wgt = (ty[i, y0:y1, None] * tx[j, None, x0:x1]).astype(np.float32)
            out[y0:y1, x0:x1] += wgt * b
    return out


# ----------------------------------------------------------------------------- NumPy reference
def render_thermal_kernel_reference(gyro_t, gyro_rate, calib: Calibration, t_frame: float, *, point=None,
                                    m: float = 5.0, psf: bool = True) -> Kernel:
    """Plain NumPy re-implementation of `render_thermal_kernel` (same signature, same result).

    Rotations at the samples come from `thermod.physics.geometry.integrate_rotations` (the reference rate
    semantics), sub-steps from `so3_exp`, offsets from `apply_homography`, weights from the
    closed-form exponential integrals, the splat from `np.add.at`. Slow; for tests and benchmarks.
    """
    t_all, r_all = _check_gyro(gyro_t, gyro_rate)
    p = _make_params(calib)
    tf = _check_scalar("t_frame", t_frame)
    x, y = _check_point(point, p)
    tau = p.tau
    a, b = _window(p, tf, y, _check_scalar("m", m, True) * tau)
    ts, rs = _window_slice(t_all, r_all, a - p.offset, b - p.offset)
    tc, wc = calib.gyro_to_camera(ts, rs)
    Qs = integrate_rotations(tc, wc, b)

    def rate(s):
        return np.array([np.interp(s, tc, wc[:, i]) for i in range(3)])

    inside = (tc > a) & (tc < b)
    bt = np.r_[a, tc[inside], b]
    bQ = [None] + [Qs[i] for i in np.nonzero(inside)[0]] + [np.eye(3)]
    ppr = _px_per_rad(p, x, y)
    times, Qn = [], []
    for k in range(len(bt) - 1):
        s0, s1 = bt[k], bt[k + 1]
        w0, w1 = rate(s0), rate(s1)
        move = ppr * max(np.linalg.norm(w0), np.linalg.norm(w1)) * (s1 - s0)
        n = max(1, int(math.ceil(move / MAX_STEP_PX)))
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
    pt = np.array([[x, y]])
    u = np.array([pt[0] - apply_homography(_K_of(p) @ Q @ np.linalg.inv(_K_of(p)), pt)[0] for Q in Qn])
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
    if psf and p.psf_sigma > 0:
        from scipy.signal import convolve2d
        g = optical_psf(p.psf_sigma)
        k = convolve2d(k, g.weights.astype(np.float64), mode="full")
        oy, ox = oy + g.origin[0], ox + g.origin[1]
    lo, hi = max(a, tc[0]), min(b, tc[-1])
    cov = 0.0 if hi <= lo else (np.exp(-(b - hi) / tau) - np.exp(-(b - lo) / tau)) / -np.expm1(-(b - a) / tau)
    ns = int(((tc > a) & (tc <= b)).sum())
    return Kernel(k.astype(np.float32), (int(oy), int(ox)), float(min(cov, 1.0)), ns)


def _K_of(p: _Params) -> np.ndarray:
    return np.array([[p.fx, 0.0, p.cx], [0.0, p.fy, p.cy], [0.0, 0.0, 1.0]])
