"""Fine sync: offset, misalignment, gyro bias, clock drift and readout by robust least squares.

Weighted robust least squares (Huber) of the picture rotations φ_k against the gyro's, integrated over
each interval: φ̂_k = exp([δ]×) M (∫ ω_τ(t − off − ε (t − t_mid)) dt − b Δt) with the offset off at the
video's middle t_mid, the clocks' rate difference ε (fitted on videos of ≥ 5 s), a small misalignment δ
(≤ 0.2 rad) on top of the mount and the gyro bias b (gyro frame), for the best few mounts by correlation
(the lowest cost wins). Then the rolling readout: the rotation is also fitted on three horizontal bands
alone, and band b's rows are read lead_b·readout before the frame time, so where the rate changes the
bands see it at times a share of the readout apart. Uncertainties: a delete-one-block jackknife over 8
contiguous stretches of the video (residuals are correlated in time, so the fit's own covariance would
be optimistic). The picture's apparent lag (up to τ, `thermod.motion.picture`) is common to every band,
so it does not bias the readout, but it bounds the offset by ½ τ (`FineSync.lag_bound_s`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from thermod.motion.picture import PictureMotion
from thermod.physics.geometry import so3_exp
from thermod.sync.coarse import MOUNTS, CoarseSync
from thermod.sync.gyro import _exp_filter, _gyro_grid, cumulative_rotation

MAX_MISALIGNMENT_RAD = 0.2    # the fine fit's rotation on top of an axis-aligned mount (11.5°)
MAX_DRIFT = 0.005             # the clocks' rate difference the fine fit allows (5000 ppm)
MIN_DRIFT_VIDEO_S = 5.0       # ... fitted on videos at least this long (else held at 0)


@dataclass
class FineSync:
    """Offset, rotation (mount ⊕ misalignment) and bias fitted to the picture rotations.

    The σ are delete-one-block jackknife standard errors. `lag_bound_s` is the systematic bound on the
    offset from the picture's apparent lag (module docstring: ½ τ). `cost` is the robust weighted cost
    of the fit (χ² units), `mount_costs` that of every mount tried."""

    time_offset_s: float
    time_offset_sigma_s: float
    lag_bound_s: float
    misalignment_rad: np.ndarray
    misalignment_sigma_rad: np.ndarray
    bias_rad_s: np.ndarray
    bias_sigma_rad_s: np.ndarray
    R_cam_gyro: np.ndarray
    mount_index: int
    residual_rms_rad_s: float
    picture_rms_rad_s: float
    n_intervals: int
    cost: float
    mount_costs: dict = field(default_factory=dict)
    readout_s: float = 0.0
    readout_sigma_s: float = math.nan       # NaN: not fitted (bands too sparse, or not asked)
    clock_drift_ppm: float = 0.0            # the gyro clock runs at 1 + ε against the video's
    clock_drift_sigma_ppm: float = math.nan  # NaN: not fitted (a video shorter than MIN_DRIFT_VIDEO_S)
    clock_epoch_video_s: float = 0.0        # where `time_offset_s` holds: the video's middle (video clock)


class _GyroIntegral:
    """∫ of the τ-filtered gyro over any interval, on a uniform fine grid around the video."""

    def __init__(self, gyro_t, gyro_rate, t_lo: float, t_hi: float, tau_s: float):
        dt_log = float(np.median(np.diff(gyro_t)))
        self.h = h = min(dt_log, 1e-3)
        n = int(math.ceil((t_hi - t_lo) / h)) + 1
        G = cumulative_rotation(gyro_t, gyro_rate)
        rate = _exp_filter(_gyro_grid(gyro_t, G, t_lo, h, n), h, tau_s)
        self.G = np.r_[np.zeros((1, 3)), np.cumsum(rate * h, axis=0)]
        self.grid = t_lo + (np.arange(n + 1) - 0.5) * h

    def integral(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        Ga = np.stack([np.interp(a, self.grid, self.G[:, i]) for i in range(3)], axis=1)
        Gb = np.stack([np.interp(b, self.grid, self.G[:, i]) for i in range(3)], axis=1)
        return Gb - Ga


class FineProblem:
    """φ against exp([δ]×) M (∫ω_τ − b Δt) over the measured intervals, each whitened by its information.

    x = (offset, δ (3), bias (3), clock drift ε[, readout]): the gyro's time for camera time t is
    t − offset − ε (t − t_mid), t_mid the middle of the video (the epoch), as `Calibration`'s clock
    drift has it. Whole frames (`bands` False): the rows are read ½ readout before the frame time on
    average, the readout fixed. Bands: each band's rotation over its own rows' read times (lead ·
    readout before), the readout a parameter (x[8]) in [0, one frame period]: a rate that changes
    shows up in the bands at times that differ by a share of the readout."""

    def __init__(self, pm: PictureMotion, gyro_t, gyro_rate, offset_s: float, tau_s: float, readout_s: float,
                 bands: bool = False):
        if bands:
            ok = np.all(np.isfinite(pm.band_rotvec), axis=2)
            k, j = np.nonzero(ok)
            self.phi, info, self.lead = pm.band_rotvec[k, j], pm.band_info[k, j], pm.band_lead[k, j]
        else:
            k = np.flatnonzero(pm.valid)
            self.phi, info, self.lead = pm.rotvec[k], pm.info[k], np.full(len(k), 0.5)
        self.interval = k
        self.t0, self.t1 = pm.t0[k], pm.t1[k]
        self.t_mid = 0.5 * (float(pm.t0[0]) + float(pm.t1[-1]))
        self.since_mid = 0.5 * (self.t0 + self.t1) - self.t_mid
        self.fit_readout = bands
        self.readout_s = readout_s
        self.period = float(np.median(pm.t1 - pm.t0))
        span = max(1.0, 0.25 * (self.t1[-1] - self.t0[0]))
        lo = max(self.t0[0] - self.period - offset_s - span, float(gyro_t[0]))
        hi = min(self.t1[-1] - offset_s + span, float(gyro_t[-1]))
        self.gi = _GyroIntegral(gyro_t, gyro_rate, lo, hi, tau_s)
        self.L = np.linalg.cholesky(info).transpose(0, 2, 1)           # ‖L r‖² = rᵀ info r
        self.dts = self.t1 - self.t0
        n = 9 if bands else 8
        # a short video's drift would only take up model error (a bound of 1e-12 holds it at 0)
        self.fit_drift = self.t1[-1] - self.t0[0] >= MIN_DRIFT_VIDEO_S
        drift = MAX_DRIFT if self.fit_drift else 1e-12
        self.scale = np.r_[1e-3, [1e-2] * 6, 1e-5, 1e-3][:n]
        self.lower = np.r_[-np.inf, [-MAX_MISALIGNMENT_RAD] * 3, [-np.inf] * 3, -drift, 0.0][:n]
        self.upper = np.r_[np.inf, [MAX_MISALIGNMENT_RAD] * 3, [np.inf] * 3, drift, self.period][:n]

    def start(self, offset_s: float, x=None) -> np.ndarray:
        x0 = np.r_[offset_s, np.zeros(7)] if x is None else np.asarray(x[:8], float)
        return np.r_[x0, self.readout_s] if self.fit_readout else x0

    def predicted(self, x, M, sel=slice(None)):
        ro = x[8] if self.fit_readout else self.readout_s
        shift = x[0] + x[7] * self.since_mid[sel] + ro * self.lead[sel]
        ig = self.gi.integral(self.t0[sel] - shift, self.t1[sel] - shift) - x[4:7] * self.dts[sel, None]
        return ig @ (so3_exp(x[1:4]) @ M).T

    def residual(self, x, M, sel=slice(None)):
        return np.einsum("nij,nj->ni", self.L[sel], self.phi[sel] - self.predicted(x, M, sel)).ravel()

    def fit(self, x_start, M, sel=slice(None)):
        """Robust (Huber) fit from `x_start`; returns (x, cost)."""
        from scipy.optimize import least_squares

        inset = 1e-3 * np.minimum(self.upper - self.lower, 1.0)
        x = np.clip(x_start, self.lower + inset, self.upper - inset)
        r0 = self.residual(x, M, sel)
        f_scale = 3.0 * max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-9)
        for _ in range(2):
            sol = least_squares(self.residual, x, args=(M, sel), loss="huber", f_scale=f_scale,
                                x_scale=self.scale, method="trf", bounds=(self.lower, self.upper))
            x = sol.x
        return x, float(sol.cost)

    def jackknife(self, x, M, blocks: int) -> np.ndarray:
        """Delete-one-block jackknife standard errors over `blocks` contiguous stretches of the video."""
        ivals = np.unique(self.interval)
        edges = ivals[np.linspace(0, len(ivals) - 1, blocks + 1).astype(int)]
        edges[-1] += 1
        jk = []
        for b in range(blocks):
            sel = ~((self.interval >= edges[b]) & (self.interval < edges[b + 1]))
            jk.append(self.fit(x, M, sel)[0])
        jk = np.array(jk)
        return np.sqrt((blocks - 1) / blocks * np.sum((jk - jk.mean(axis=0)) ** 2, axis=0))


def refine(pm: PictureMotion, gyro_t, gyro_rate, coarse: CoarseSync, *, tau_s: float = 0.0,
           readout_s: float = 0.0, mounts: tuple[int, ...] | None = None, fit_readout: bool = True,
           blocks: int = 8) -> FineSync:
    """Stage 3 (module docstring): offset, misalignment and bias by robust weighted least squares, for
    each mount in `mounts` (default: the coarse one and every mount whose correlation came within 0.05
    of it); the mount with the lowest cost wins (a mount differing only about an axis the motion
    barely turns correlates almost as well, but fits worse). Then, with `fit_readout` and bands measured
    in at least half the intervals, the readout time too, on the bands."""
    from threadpoolctl import threadpool_limits

    # Each fit factors a few-thousand × 8 Jacobian: BLAS threads only contend for it (5× slower measured
    # on a loaded 2-core machine).
    with threadpool_limits(1):
        return _refine(pm, gyro_t, gyro_rate, coarse, tau_s, readout_s, mounts, fit_readout, blocks)


def _refine(pm, gyro_t, gyro_rate, coarse, tau_s, readout_s, mounts, fit_readout, blocks) -> FineSync:
    if mounts is None:
        best = coarse.ncc_curves.max(axis=1)
        near = np.argsort(best)[::-1]
        mounts = tuple(int(i) for i in near[:4] if best[i] >= coarse.ncc - 0.05)
    prob = FineProblem(pm, gyro_t, gyro_rate, coarse.time_offset_s, tau_s, readout_s)
    x0 = prob.start(coarse.time_offset_s)
    fits = {i: prob.fit(x0, MOUNTS[i]) for i in mounts}
    mi = min(fits, key=lambda i: fits[i][1])
    M = MOUNTS[mi]
    x, cost = fits[mi]
    banded = np.sum(np.all(np.isfinite(pm.band_rotvec), axis=2), axis=1) >= 2
    readout_sigma = math.nan
    if fit_readout and banded.sum() >= 0.5 * len(banded):
        prob = FineProblem(pm, gyro_t, gyro_rate, x[0], tau_s, readout_s, bands=True)
        x, _ = prob.fit(prob.start(x[0], x), M)
        sigma = prob.jackknife(x, M, blocks)
        readout, readout_sigma = float(x[8]), float(sigma[8])
    else:
        sigma = prob.jackknife(x, M, blocks)
        readout = readout_s
    whole = FineProblem(pm, gyro_t, gyro_rate, x[0], tau_s, readout)
    R = so3_exp(x[1:4]) @ M
    res_rate = (whole.phi - whole.predicted(x[:8], M)) / whole.dts[:, None]
    return FineSync(float(x[0]), float(sigma[0]), 0.5 * tau_s, x[1:4].copy(), sigma[1:4].copy(),
                    x[4:7].copy(), sigma[4:7].copy(), R, mi, float(np.sqrt(np.mean(res_rate**2))),
                    float(np.sqrt(np.mean((whole.phi / whole.dts[:, None]) ** 2))), len(whole.phi), cost,
                    {int(i): c for i, (_, c) in fits.items()}, readout, readout_sigma,
                    float(x[7] * 1e6) if whole.fit_drift else 0.0,
                    float(sigma[7] * 1e6) if whole.fit_drift else math.nan, whole.t_mid)
