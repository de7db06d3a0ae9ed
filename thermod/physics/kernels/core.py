"""The numba core of the kernel renderer: gyro path → nodes and weights → offsets → splat → PSF.

Scalar arguments travel in plain tuples whose layouts are the NamedTuples below (`PathWindow`,
`PathSampling`, `Pinhole`): numba types a plain tuple of scalars as fast as loose arguments but a
NamedTuple instance ~15 µs slower per call, so callers pass plain tuples in field order and the
jitted code names the fields with ``PathWindow(*window)``. Every entry point returns a
`PathStatus` value (an int at the boundary: boxing the enum member costs ~5 µs).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple

import numpy as np
from numba import njit

from thermod.physics.geometry import jit_cores, so3_exp_into

jit_cores()   # the geometry's Rodrigues map, callable from the jitted code below


class PathStatus(IntEnum):
    """Why a jitted renderer stopped (OK = it did not)."""

    OK = 0
    TOO_MANY_NODES = 1          # the path needs more than PathSampling.max_nodes nodes
    BEHIND_CAMERA = 2           # a ray turned behind the camera (> 90° within the window)
    TOO_LARGE = 3               # the kernel would exceed PathSampling.max_size_px
    NONFINITE_TIMES = 4
    TIMES_NOT_INCREASING = 5
    NONFINITE_RATES = 6


class PathWindow(NamedTuple):
    """The time window (a, b] of one kernel, camera clock, and its weighting."""

    start: float                # a
    end: float                  # b: the read time of the kernel's row; Q(b) = I
    tau: float                  # thermal time constant (s) of the exponential weight (Eq. 18)
    box: bool                   # equal weights instead (photon detector, Eq. 17)


class PathSampling(NamedTuple):
    """How finely the path is sampled and how large it may grow."""

    px_per_rad: float           # bound on image speed per rad/s over the frame (px)
    max_step_px: float          # largest image motion between consecutive nodes (Eq. 12)
    max_nodes: int
    max_size_px: int            # largest kernel side


class Pinhole(NamedTuple):
    fx: float
    fy: float
    cx: float
    cy: float


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
def _hat_weights(x, y, b, tau, box):
    """∫ over [x, y] of the window weight times the hats (1−λ, λ), λ = (s−x)/(y−x).

    Exponential: e(s) = exp(−(b − s)/τ) (Eq. 18, continuous form); uniform: e = 1 (Eq. 17).
    """
    h = y - x
    if box:
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



@njit(cache=True, nogil=True, inline="always")
def _calibrated_samples(t_all, r_all, M, bias, offset, a, b):
    """The samples around [a, b] (camera clock) plus one neighbour each side, calibrated:
    times t + offset and rates ω_cam = M (ω_gyro − bias). Returns (t, ω, status)."""
    m_all = t_all.shape[0]
    i0 = max(np.searchsorted(t_all, a - offset, side="right") - 1, 0)
    i1 = min(np.searchsorted(t_all, b - offset, side="left") + 1, m_all)
    if i1 <= i0:   # all samples on one side of the window: keep the nearest one (its rate is held)
        i0, i1 = (m_all - 1, m_all) if i0 >= m_all - 1 else (0, 1)
    n = i1 - i0
    t = np.empty(n)
    w = np.empty((n, 3))
    for i in range(n):
        ti = t_all[i0 + i]
        if not math.isfinite(ti):
            return t, w, PathStatus.NONFINITE_TIMES.value
        if i > 0 and not ti > t_all[i0 + i - 1]:
            return t, w, PathStatus.TIMES_NOT_INCREASING.value
        t[i] = ti + offset
        d0 = r_all[i0 + i, 0] - bias[0]
        d1 = r_all[i0 + i, 1] - bias[1]
        d2 = r_all[i0 + i, 2] - bias[2]
        if not (math.isfinite(d0) and math.isfinite(d1) and math.isfinite(d2)):
            return t, w, PathStatus.NONFINITE_RATES.value
        for r in range(3):
            w[i, r] = M[r, 0] * d0 + M[r, 1] * d1 + M[r, 2] * d2
    return t, w, PathStatus.OK.value


@njit(cache=True, nogil=True, inline="always")
def _stretches(t, w, a, b):
    """Stretch boundaries a, the samples strictly inside (a, b), b, with their rates; and the
    number of samples in (a, b]."""
    n_in = 0
    n_samples = 0
    for i in range(t.shape[0]):
        if t[i] > a and t[i] < b:
            n_in += 1
        if t[i] > a and t[i] <= b:
            n_samples += 1
    bt = np.empty(n_in + 2)
    bw = np.empty((n_in + 2, 3))
    bt[0] = a
    _rate_at(t, w, a, bw[0])
    j = 1
    for i in range(t.shape[0]):
        if t[i] > a and t[i] < b:
            bt[j] = t[i]
            bw[j, :] = w[i, :]
            j += 1
    bt[n_in + 1] = b
    _rate_at(t, w, b, bw[n_in + 1])
    return bt, bw, n_samples


@njit(cache=True, nogil=True, inline="always")
def _substeps(bt, bw, sampling):
    """Sub-steps per stretch so the image moves ≤ max_step_px per step (bound: px_per_rad·|ω|·Δs);
    returns (counts, total nodes, status)."""
    smp = PathSampling(*sampling)
    nsub = np.empty(bt.shape[0] - 1, dtype=np.int64)
    total = 1
    for k in range(bt.shape[0] - 1):
        m0 = math.sqrt(bw[k, 0] ** 2 + bw[k, 1] ** 2 + bw[k, 2] ** 2)
        m1 = math.sqrt(bw[k + 1, 0] ** 2 + bw[k + 1, 1] ** 2 + bw[k + 1, 2] ** 2)
        move = smp.px_per_rad * max(m0, m1) * (bt[k + 1] - bt[k])
        nsub[k] = max(1, int(math.ceil(move / smp.max_step_px)))
        total += nsub[k]
        if total > smp.max_nodes:
            return nsub, total, PathStatus.TOO_MANY_NODES.value
    return nsub, total, PathStatus.OK.value


@njit(cache=True, nogil=True)
def _node_rotations(bt, bw, nsub, total):
    """Node times and Q(s) = R(b)ᵀR(s), every sub-node taken from its stretch's end node s1 by one
    trapezoid step Q(s) = Q(s1) exp(½(ω(s)+ω(s1))(s−s1)), so at the samples Q equals
    `integrate_rotations` exactly (tests/physics/test_kernels.py checks it).

    This is `geometry.trapezoid_step_into` written on scalars: passing array views per node costs
    ~25 % of the renderer's time here. The Rodrigues map is the geometry's `so3_exp_into`.
    """
    times = np.empty(total)
    Q = np.empty((total, 3, 3))
    E = np.empty((3, 3))
    idx = total - 1
    times[idx] = bt[bt.shape[0] - 1]
    Q[idx] = np.eye(3)
    for k in range(bt.shape[0] - 2, -1, -1):
        s0 = bt[k]
        s1 = bt[k + 1]
        end = idx
        for jj in range(nsub[k] - 1, -1, -1):
            s = s0 + (s1 - s0) * jj / nsub[k]
            f = (s - s0) / (s1 - s0)
            h = 0.5 * (s - s1)
            so3_exp_into(h * (bw[k, 0] + f * (bw[k + 1, 0] - bw[k, 0]) + bw[k + 1, 0]),
                         h * (bw[k, 1] + f * (bw[k + 1, 1] - bw[k, 1]) + bw[k + 1, 1]),
                         h * (bw[k, 2] + f * (bw[k + 1, 2] - bw[k, 2]) + bw[k + 1, 2]), E)
            idx -= 1
            times[idx] = s
            for r in range(3):
                for c in range(3):
                    Q[idx, r, c] = Q[end, r, 0] * E[0, c] + Q[end, r, 1] * E[1, c] + Q[end, r, 2] * E[2, c]
    return times, Q


@njit(cache=True, nogil=True, inline="always")
def _node_weights(times, win):
    """Quadrature weights: each sub-interval's window weight against the hats at its ends, sum 1."""
    wt = np.zeros(times.shape[0])
    acc = 0.0
    for i in range(times.shape[0] - 1):
        wl, wr = _hat_weights(times[i], times[i + 1], win.end, win.tau, win.box)
        wt[i] += wl
        wt[i + 1] += wr
        acc += wl + wr
    for i in range(times.shape[0]):
        wt[i] /= acc
    return wt


@njit(cache=True, nogil=True, inline="always")
def _coverage(t, win):
    """Share of the window's weight inside [first sample, last sample]."""
    a, b, tau = win.start, win.end, win.tau
    lo = max(a, t[0])
    hi = min(b, t[t.shape[0] - 1])
    if hi <= lo:
        return 0.0
    if win.box:
        return min((hi - lo) / (b - a), 1.0)
    cov = (math.exp(-(b - hi) / tau) - math.exp(-(b - lo) / tau)) / (1.0 - math.exp(-(b - a) / tau))
    return min(cov, 1.0)


@njit(cache=True, nogil=True)
def path_nodes(t_all, r_all, M, bias, offset, window, sampling):
    """Rotations Q(s) = R(b)ᵀR(s) and normalised quadrature weights at sub-nodes of (a, b].

    t_all, r_all: raw gyro samples (a whole ring may be passed: only the window's are read);
    M, bias, offset: the gyro → camera map ω_cam = M (ω_gyro − bias) at camera time t + offset;
    window: a `PathWindow`, sampling: a `PathSampling` (plain tuples). The rate is piecewise linear
    between samples and held outside them. Returns (times, Q, w, coverage, n_samples, status).
    """
    win = PathWindow(*window)
    t, w, st = _calibrated_samples(t_all, r_all, M, bias, offset, win.start, win.end)
    if st != PathStatus.OK.value:
        return np.empty(0), np.empty((0, 3, 3)), np.empty(0), 0.0, 0, st
    bt, bw, n_samples = _stretches(t, w, win.start, win.end)
    nsub, total, st = _substeps(bt, bw, sampling)
    if st != PathStatus.OK.value:
        return np.empty(0), np.empty((0, 3, 3)), np.empty(0), 0.0, n_samples, st
    times, Q = _node_rotations(bt, bw, nsub, total)
    return times, Q, _node_weights(times, win), _coverage(t, win), n_samples, PathStatus.OK.value


@njit(cache=True, nogil=True)
def path_offsets(Q, point, camera):
    """u_i = p − π(K Q_i K⁻¹ p) (Eq. 16) at point (x, y) as [n, 2] (u_x, u_y), with status."""
    px, py = point
    cam = Pinhole(*camera)
    n = Q.shape[0]
    u = np.empty((n, 2))
    dx = (px - cam.cx) / cam.fx
    dy = (py - cam.cy) / cam.fy
    for i in range(n):
        q0 = Q[i, 0, 0] * dx + Q[i, 0, 1] * dy + Q[i, 0, 2]
        q1 = Q[i, 1, 0] * dx + Q[i, 1, 1] * dy + Q[i, 1, 2]
        q2 = Q[i, 2, 0] * dx + Q[i, 2, 1] * dy + Q[i, 2, 2]
        if q2 <= 1e-6:
            return u, PathStatus.BEHIND_CAMERA.value
        u[i, 0] = px - (cam.fx * q0 / q2 + cam.cx)
        u[i, 1] = py - (cam.fy * q1 / q2 + cam.cy)
    return u, PathStatus.OK.value


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
        return np.zeros((1, 1)), 0, 0, PathStatus.TOO_LARGE.value
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
    return k, -ymin, -xmin, PathStatus.OK.value


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
def kernel_at(Q, w, point, camera, max_size, g):
    """Offsets at `point`, bilinear splat, PSF (g: 1-D taps; length 1 = none) → float32 kernel.

    Returns (weights, oy, ox, status).
    """
    u, st = path_offsets(Q, point, camera)
    if st != PathStatus.OK.value:
        return np.zeros((1, 1), dtype=np.float32), 0, 0, st
    k, oy, ox, st = _splat(u, w, max_size)
    if st != PathStatus.OK.value:
        return np.zeros((1, 1), dtype=np.float32), 0, 0, st
    r = g.shape[0] // 2
    if r == 0:
        return k.astype(np.float32), oy, ox, PathStatus.OK.value
    return _convolve_sep(k, g), oy + r, ox + r, PathStatus.OK.value


@njit(cache=True, nogil=True)
def render_one(t_all, r_all, M, bias, offset, window, sampling, point, camera, g):
    """`path_nodes` then `kernel_at` in one call (one dispatch per kernel)."""
    times, Q, w, cov, ns, st = path_nodes(t_all, r_all, M, bias, offset, window, sampling)
    if st != PathStatus.OK.value:
        return np.zeros((1, 1), dtype=np.float32), 0, 0, cov, ns, st
    k, oy, ox, st = kernel_at(Q, w, point, camera, PathSampling(*sampling).max_size_px, g)
    return k, oy, ox, cov, ns, st
