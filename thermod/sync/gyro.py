"""The gyro side of a sync: checked input arrays, the rate's integral and its mean over a uniform grid
through the detector's exponential response (Eq. 10)."""

from __future__ import annotations

import math

import numpy as np

from thermod.sync.errors import SyncInputError


def _check_arrays(frame_t, gyro_t, gyro_rate, n_frames: int | None = None):
    t = np.asarray(frame_t, dtype=np.float64)
    gt = np.asarray(gyro_t, dtype=np.float64)
    gr = np.asarray(gyro_rate, dtype=np.float64)
    if t.ndim != 1 or len(t) < 2:
        raise SyncInputError(f"frame_t: expected ≥ 2 frame times, got shape {t.shape}")
    if n_frames is not None and len(t) != n_frames:
        raise SyncInputError(f"frame_t: expected one time per frame ({n_frames}), got {len(t)}")
    if gt.ndim != 1 or len(gt) < 4:
        raise SyncInputError(f"gyro_t: expected ≥ 4 gyro sample times, got shape {gt.shape}")
    if gr.shape != (len(gt), 3):
        raise SyncInputError(f"gyro_rate: expected shape ({len(gt)}, 3) (rad/s, matching gyro_t), got "
                             f"{gr.shape}")
    for name, a in (("frame_t", t), ("gyro_t", gt), ("gyro_rate", gr)):
        if not np.all(np.isfinite(a)):
            raise SyncInputError(f"{name}: contains NaN or infinite values")
    for name, a in (("frame_t", t), ("gyro_t", gt)):
        if not np.all(np.diff(a) > 0):
            i = int(np.flatnonzero(np.diff(a) <= 0)[0]) + 1
            raise SyncInputError(f"{name}: times must increase; index {i} ({a[i]!r}) follows {a[i - 1]!r}")
    return t, gt, gr


def cumulative_rotation(gyro_t: np.ndarray, gyro_rate: np.ndarray) -> np.ndarray:
    """∫ω dt from the first sample (trapezoid: the rate linear between samples), [M, 3]."""
    dt = np.diff(gyro_t)[:, None]
    return np.r_[np.zeros((1, 3)), np.cumsum(0.5 * (gyro_rate[1:] + gyro_rate[:-1]) * dt, axis=0)]


def _exp_filter(x: np.ndarray, h: float, tau: float) -> np.ndarray:
    """Causal first-order response (the detector's Eq. 10 IIR) of a uniformly sampled signal."""
    if tau <= 0:
        return x
    from scipy.signal import lfilter
    a = math.exp(-h / tau)
    zi = (x[:1] * a)
    y, _ = lfilter([1.0 - a], [1.0, -a], x, axis=0, zi=zi)
    return y


def _gyro_grid(gyro_t, G, t_lo: float, h: float, n: int) -> np.ndarray:
    """Mean rate over [t_lo + i h − h/2, t_lo + i h + h/2) for i < n, from the cumulative integral."""
    edges = t_lo + (np.arange(n + 1) - 0.5) * h
    Ge = np.stack([np.interp(edges, gyro_t, G[:, a]) for a in range(3)], axis=1)
    return np.diff(Ge, axis=0) / h
