"""Sync a thermal video to a flight-controller gyro log from the pictures alone.

Nothing tells where in a long log the video sits, nor how the camera is mounted on the flight
controller. `synchronise` finds both, on arrays (the readers of video containers and log formats are
elsewhere), in three stages:

1. **Picture motion** (`picture_motion`). Each frame is normalised on its own to zero mean and unit
   standard deviation (a robust one: the median and the 1–99 % spread), which removes an automatic
   gain control's per-frame gain and offset exactly whenever it is a global affine map of the counts;
   then it is shrunk to a working width (≈ 160 px) and mapped to 8 bits. Shi–Tomasi corners of frame
   k−1 are tracked into frame k by pyramidal Lucas–Kanade, kept when the backward track returns within
   0.5 px, and turned into rays v = K⁻¹p/‖K⁻¹p‖. The camera's rotation between the frames,
   Q = R(t_{k−1})ᵀ R(t_k) with v_{k−1} = Q v_k (docs/design.md §2), is the orthogonal Procrustes
   (Kabsch) fit on the rays, inside a two-point RANSAC; its rotation vector φ_k ≈ ∫ω dt over the
   interval, in the camera frame, with the information matrix Σ [v]×ᵀ[v]× / σ² from the fit's
   residual σ (rad).
2. **Coarse** (`coarse_sync`). The picture rate φ_k/Δt_k (piecewise constant on the video clock) and
   the gyro's rate (box means over a uniform grid of step h from its cumulative integral, filtered by
   the detector's exponential response τ, Eq. 10; a picture row is read `readout_s`·½ before the frame
   time on average) are cross-correlated by FFT over the whole log, for all nine axis pairs at once;
   each of the 24 axis-aligned mounts M (entries in {−1, 0, 1}, det +1; `MOUNTS`) is a signed sum of
   those nine. The normalised correlation (Pearson, the gyro's window mean removed at every lag, so a
   gyro bias does not count) picks the lag and the mount; a parabola through the peak refines the lag
   below h. Conventions: ω_cam = M ω_gyro, t_cam = t_gyro + time_offset_s.
3. **Fine** (`refine`). Weighted robust least squares (Huber) of the picture rotations φ_k against the
   gyro's, integrated over each interval: φ̂_k = exp([δ]×) M (∫ ω_τ(t − off − ε (t − t_mid)) dt − b Δt)
   with the offset off at the video's middle t_mid, the clocks' rate difference ε (a video stamped at
   its nominal frame rate drifts against the log; fitted on videos of ≥ 5 s), a small misalignment δ
   (≤ 0.2 rad) on top of the mount and the gyro bias b (gyro frame), for the best few mounts by
   correlation (the lowest cost wins: a mount that differs only about an axis the motion barely turns
   correlates almost as well, but fits worse). Then the rolling readout: the rotation is also fitted on
   the corners of three horizontal bands alone, and band b's rows are read lead_b·readout before the
   frame time (lead = 1 − (row + 1)/H), so where the rate changes the bands see it at times a share of
   the readout apart; the readout joins the fit (0 to one frame period). Uncertainties: a
   delete-one-block jackknife over 8 contiguous stretches of the video (residuals are correlated in
   time, so the fit's own covariance would be optimistic).

The picture lags the gyro through the detector: the centroid of its exponential response is τ
behind, which the gyro's τ filter models; Lucas–Kanade on a comet-tailed corner follows the sharper
head more than the centroid, so the measured lag is shorter than τ, and by how much depends on the
blur. The frames are smoothed (σ = 1.5 working px) so the tracker sees more of the tail, and the
offset carries a systematic bound of ½ τ (`FineSync.lag_bound_s`) beside its jackknife σ. The lag is
common to every band, so it does not bias the readout. τ itself is as given (it shows only as this
lag, which the offset absorbs).

Refused, never guessed (`SyncError` subclasses): a video whose picture rotation does not rise above
its own measurement noise (`TooLittleMotion`); a log shorter than the video (`DurationMismatch`); a
log in which no place correlates significantly, or two places equally (`LogMismatch`).

The motion-only discrepancy workflow (`thermod.calib.sync_discrepancy`, `DISCREPANCY_CANDIDATES`) is
the stage that sees τ apart from the offset (through the detector's forward model), and refits the
rest on a stretch of the synced video; what it recovers at a given size is measured in
benchmarks/results/sync.md.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np

from thermod.errors import ThermodError
from thermod.physics.geometry import Intrinsics, so3_exp, so3_log

#: Candidates of the discrepancy workflow that refine what the sync found (and what it cannot).
DISCREPANCY_CANDIDATES = ("time_offset", "misalignment", "gyro_bias", "rolling_readout", "time_constant")
MIN_INTERVALS = 20            # picture intervals with a rotation estimate a sync needs
MIN_FEATURES = 8              # tracked corners a rotation estimate needs
BANDS = 3                     # horizontal bands of a frame fitted apart (rolling readout)
MIN_MOTION_SNR = 5.0          # picture rotation RMS over its measurement noise RMS
MIN_MOTION_PX = 0.25          # picture rotation RMS per interval, in working-image pixels
MIN_NCC = 0.75                # the correlation peak a log must reach (null peaks of a 3 s video: ≤ 0.63)
MIN_RESIDUAL_RATIO = 3.0      # the best place elsewhere must leave ≥ this × the peak's residual (1 − ρ²)
MIN_LOG_MOTION_RATIO = 0.2     # the log's best stretch must turn ≥ this × the video's picture rotation (RMS)
MAX_MISALIGNMENT_RAD = 0.2    # the fine fit's rotation on top of an axis-aligned mount (11.5°)
MAX_DRIFT = 0.005             # the clocks' rate difference the fine fit allows (5000 ppm)
MIN_DRIFT_VIDEO_S = 5.0       # ... fitted on videos at least this long (else held at 0)
MAX_GRID_S = 0.005            # coarse correlation grid step
MAX_GRID_SAMPLES = 1_000_000  # ... and its length over the whole log (a 1.4 h log at 5 ms)
MIN_PART_S = 3.0              # the shortest part of a video a log may cover alone (see `covered_part`)
MIN_PART_FRACTION = 0.3       # ... and of the video's length
PART_SHRINK = 0.8             # the part searched is shortened by this factor until one is found
PART_MARGIN_S = 0.1           # log kept beyond a covered part's frames (τ tails, the fine search)


def _axis_aligned_rotations() -> tuple[np.ndarray, ...]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            M = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs, strict=True)):
                M[row, col] = s
            if round(np.linalg.det(M)) == 1:
                out.append(M)
    return tuple(out)


#: The 24 proper rotations with entries in {−1, 0, 1}, the identity first.
MOUNTS: tuple[np.ndarray, ...] = _axis_aligned_rotations()


class SyncError(ThermodError):
    """The video and the gyro log could not be synced; the message says what was wrong."""


class SyncInputError(SyncError):
    """An input array has the wrong shape, type or values."""


class TooLittleMotion(SyncError):
    """The video's rotation does not rise above the noise of its own measurement."""


class DurationMismatch(SyncError):
    """The video is longer than the log that should contain it."""


class LogMismatch(SyncError):
    """No place in the log (or more than one) correlates with the video's rotation."""


# ------------------------------------------------------------------------------------ picture motion
@dataclass
class PictureMotion:
    """The camera's rotation between consecutive frames, measured from the pictures.

    Interval k runs from frame k to frame k+1 (times `t0[k]`, `t1[k]`, video clock); `rotvec[k]` is
    the rotation vector of Q = R(t0)ᵀ R(t1) in the camera frame (rad; NaN where not measured);
    `info[k]` its 3×3 information matrix (rad⁻²); `n_features[k]` the corners it was fitted on;
    `residual_px[k]` the fit's RMS reprojection residual at the working resolution.

    Rolling readout: the same rotation fitted on the corners of each of `BANDS` horizontal bands of
    the frame alone (`band_rotvec`, `band_info`; NaN where a band has too few), whose rows are read
    `band_lead[k, b]` · readout before the frame time on average (1 − (row + 1)/H over its corners)."""

    t0: np.ndarray
    t1: np.ndarray
    rotvec: np.ndarray
    info: np.ndarray
    n_features: np.ndarray
    residual_px: np.ndarray
    work: Intrinsics
    band_rotvec: np.ndarray
    band_info: np.ndarray
    band_lead: np.ndarray

    def sliced(self, i0: int, i1: int) -> PictureMotion:
        """The intervals between frames i0 … i1 − 1."""
        s = slice(i0, i1 - 1)
        return PictureMotion(self.t0[s], self.t1[s], self.rotvec[s], self.info[s], self.n_features[s],
                             self.residual_px[s], self.work, self.band_rotvec[s], self.band_info[s],
                             self.band_lead[s])

    @property
    def valid(self) -> np.ndarray:
        return np.all(np.isfinite(self.rotvec), axis=1)

    @property
    def rate(self) -> np.ndarray:
        """Mean camera-frame rate over each interval (rad/s)."""
        return self.rotvec / (self.t1 - self.t0)[:, None]

    def noise_rad(self) -> np.ndarray:
        """Per-interval RMS of the rotation estimate's error (rad, from the information matrix)."""
        out = np.full(len(self.t0), np.nan)
        for k in np.flatnonzero(self.valid):
            out[k] = math.sqrt(np.trace(np.linalg.inv(self.info[k])) / 3.0)
        return out


def normalise_frame(frame: np.ndarray) -> np.ndarray:
    """A frame's counts → float32 with median 0 and 1–99 % spread 1: a per-frame affine gain and
    offset (an AGC) drops out."""
    f = np.asarray(frame, dtype=np.float32)
    lo, med, hi = np.percentile(f, (1.0, 50.0, 99.0))
    spread = float(hi - lo)
    if not spread > 0:
        spread = float(np.std(f)) or 1.0
    return (f - np.float32(med)) / np.float32(spread)


def _to_u8(z: np.ndarray) -> np.ndarray:
    return np.clip(128.0 + 160.0 * z, 0, 255).astype(np.uint8)


def _rays(pts: np.ndarray, K_inv: np.ndarray) -> np.ndarray:
    v = np.c_[pts, np.ones(len(pts))] @ K_inv.T
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation Q minimising Σ‖a − Q b‖² over the last two axes (batched: [..., n, 3])."""
    H = np.einsum("...ni,...nj->...ij", b, a)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("...ji,...kj->...ik", Vt, U)))
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    return np.einsum("...ji,...jk,...lk->...il", Vt, D, U)


def fit_rotation(prev_rays: np.ndarray, next_rays: np.ndarray, f_px: float, rng: np.random.Generator,
                 thresh_px: float = 1.0, iterations: int = 64):
    """RANSAC (two-point) then Kabsch on the inliers: Q with prev ≈ Q next.

    Returns (Q, inlier mask, residual σ in rad) or None when fewer than `MIN_FEATURES` agree."""
    n = len(prev_rays)
    if n < MIN_FEATURES:
        return None
    pairs = rng.integers(0, n, size=(iterations, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    if len(pairs) == 0:
        return None
    Qs = _kabsch(prev_rays[pairs], next_rays[pairs])
    err = np.linalg.norm(prev_rays[None] - np.einsum("sij,nj->sni", Qs, next_rays), axis=2)
    thresh = thresh_px / f_px
    inl = err < thresh
    best = int(np.argmax(inl.sum(axis=1)))
    mask = inl[best]
    for _ in range(2):
        if mask.sum() < MIN_FEATURES:
            return None
        Q = _kabsch(prev_rays[mask], next_rays[mask])
        e = np.linalg.norm(prev_rays - next_rays @ Q.T, axis=1)
        mask = e < thresh
    if mask.sum() < MIN_FEATURES:
        return None
    res = (prev_rays - next_rays @ Q.T)[mask]
    dof = max(2 * int(mask.sum()) - 3, 1)
    sigma = math.sqrt(float(np.sum(res * res)) / dof)
    return Q, mask, max(sigma, 0.05 / f_px)       # floor: LK's precision on a textured 8-bit image


def _work_intrinsics(intr: Intrinsics, work_width: int) -> tuple[Intrinsics, float]:
    scale = min(1.0, work_width / intr.width) if intr.width > 1.5 * work_width else 1.0
    return (intr.scaled(scale) if scale != 1.0 else intr), scale


def picture_motion(frames, frame_t, intrinsics: Intrinsics, *, work_width: int = 160,
                   max_features: int = 150, seed: int = 0, smooth_px: float = 0.0,
                   progress=None) -> PictureMotion:
    """The camera rotation between consecutive frames (module docstring, stage 1).

    `frames` [N, H, W] grey, or a sequence of [H, W] frames (any integer or float type: each frame is
    normalised on its own, and read once);
    `frame_t` [N] seconds on the video clock; `intrinsics` of the full frame."""
    import cv2

    t = np.asarray(frame_t, dtype=np.float64)
    n = len(frames)
    work, scale = _work_intrinsics(intrinsics, work_width)
    K_inv = work.K_inv
    f_px = math.sqrt(work.fx * work.fy)
    rng = np.random.default_rng(seed)
    size = (work.width, work.height)
    border = np.zeros((work.height, work.width), np.uint8)
    m = max(3, work.width // 40)
    border[m:-m, m:-m] = 1
    lk = {"winSize": (15, 15), "maxLevel": 3,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}

    def prepared(k):
        z = normalise_frame(frames[k])
        if scale != 1.0:
            z = cv2.resize(z, size, interpolation=cv2.INTER_AREA)
        if smooth_px > 0:
            z = cv2.GaussianBlur(z, (0, 0), smooth_px)
            z = z / max(float(np.percentile(z, 99) - np.percentile(z, 1)), 1e-6)
        return _to_u8(z)

    rotvec = np.full((n - 1, 3), np.nan)
    info = np.zeros((n - 1, 3, 3))
    nfeat = np.zeros(n - 1, dtype=np.int64)
    resid = np.full(n - 1, np.nan)
    brot = np.full((n - 1, BANDS, 3), np.nan)
    binfo = np.zeros((n - 1, BANDS, 3, 3))
    blead = np.full((n - 1, BANDS), np.nan)
    row_full = lambda y: (y + 0.5) / scale - 0.5        # noqa: E731  (working row → full-frame row)
    prev = prepared(0)
    for k in range(1, n):
        cur = prepared(k)
        p0 = cv2.goodFeaturesToTrack(prev, max_features, 0.005, max(3, work.width // 40), mask=border,
                                     blockSize=5)
        if p0 is not None and len(p0) >= MIN_FEATURES:
            p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
            pb, stb, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, **lk)
            ok = (st[:, 0] == 1) & (stb[:, 0] == 1) & (np.linalg.norm((pb - p0)[:, 0], axis=1) < 0.5)
            a, b = p0[ok, 0].astype(np.float64), p1[ok, 0].astype(np.float64)
            fit = fit_rotation(_rays(a, K_inv), _rays(b, K_inv), f_px, rng) if len(a) else None
            if fit is not None:
                Q, mask, sigma = fit
                rotvec[k - 1] = so3_log(Q)
                ra, rb = _rays(a, K_inv)[mask], _rays(b, K_inv)[mask]
                info[k - 1] = _information(rb, sigma)
                nfeat[k - 1] = int(mask.sum())
                resid[k - 1] = sigma * f_px
                band = np.minimum((b[mask, 1] / work.height * BANDS).astype(int), BANDS - 1)
                lead = 1.0 - (row_full(b[mask, 1]) + 1.0) / intrinsics.height
                for j in range(BANDS):
                    sel = band == j
                    if sel.sum() >= MIN_FEATURES:
                        brot[k - 1, j] = so3_log(_kabsch(ra[sel], rb[sel]))
                        binfo[k - 1, j] = _information(rb[sel], sigma)
                        blead[k - 1, j] = float(np.mean(lead[sel]))
        prev = cur
        if progress is not None:
            progress(k, n - 1)
    return PictureMotion(t[:-1].copy(), t[1:].copy(), rotvec, info, nfeat, resid, work, brot, binfo, blead)


def _information(rays: np.ndarray, sigma: float) -> np.ndarray:
    """Information matrix of a rotation fitted on `rays` with residual σ (rad): the residual
    a − Q b moves by −[Q b]× δ under a small rotation δ, so JᵀJ = Σ [v]×ᵀ[v]× = Σ (I − v vᵀ)."""
    return (len(rays) * np.eye(3) - rays.T @ rays) / sigma**2


def check_motion(pm: PictureMotion) -> dict:
    """Refuse a video whose rotation does not rise above its measurement noise (`TooLittleMotion`);
    returns the numbers it judged by."""
    valid = pm.valid
    nv = int(valid.sum())
    n = len(valid)
    if nv < MIN_INTERVALS:
        raise TooLittleMotion(f"video: the camera rotation could be measured between only {nv} of {n} frame "
                              f"pairs (need ≥ {MIN_INTERVALS}): too few frames, or too little texture to "
                              "track")
    phi = pm.rotvec[valid]
    noise = pm.noise_rad()[valid]
    signal_rms = float(np.sqrt(np.mean(np.sum(phi**2, axis=1)) / 3.0))
    noise_rms = float(np.sqrt(np.mean(noise**2)))
    f_px = math.sqrt(pm.work.fx * pm.work.fy)
    stats = {"intervals": n, "measured": nv, "rotation_rms_rad": signal_rms, "noise_rms_rad": noise_rms,
             "snr": signal_rms / noise_rms if noise_rms > 0 else math.inf, "motion_px": signal_rms * f_px}
    if stats["snr"] < MIN_MOTION_SNR or stats["motion_px"] < MIN_MOTION_PX:
        raise TooLittleMotion(
            f"video: too little rotation to sync: {math.degrees(signal_rms):.3g}° RMS per frame interval "
            f"({stats['motion_px']:.2f} px at {pm.work.width} px wide) against a measurement noise of "
            f"{math.degrees(noise_rms):.3g}° (need ≥ {MIN_MOTION_SNR:g}× the noise and ≥ {MIN_MOTION_PX} px);"
            " "
            "choose a stretch where the camera turns")
    return stats


# ----------------------------------------------------------------------------------------- gyro side
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


# --------------------------------------------------------------------------------------------- coarse
@dataclass
class CoarseSync:
    """The whole-log correlation: offset, mount and how clearly they won.

    `lags_s` are candidate time offsets (t_cam = t_gyro + offset); `ncc[i]` the normalised correlation
    of mount i at each (for the figure)."""

    time_offset_s: float
    mount_index: int
    ncc: float
    ncc_second_mount: float
    second_mount_index: int
    ncc_elsewhere: float
    grid_s: float
    lags_s: np.ndarray
    ncc_curves: np.ndarray

    @property
    def mount(self) -> np.ndarray:
        return MOUNTS[self.mount_index]

    @property
    def mount_margin(self) -> float:
        return self.ncc - self.ncc_second_mount

    @property
    def residual_ratio(self) -> float:
        """(1 − ρ²) of the best place more than a second from the peak over that of the peak."""
        if self.ncc_elsewhere <= -1.0:
            return math.inf
        return (1.0 - max(self.ncc_elsewhere, 0.0) ** 2) / max(1.0 - self.ncc**2, 1e-12)


def coarse_sync(pm: PictureMotion, gyro_t, gyro_rate, *, tau_s: float = 0.0, readout_s: float = 0.0,
                grid_s: float | None = None) -> CoarseSync:
    """Offset and mount by the best normalised cross-correlation over the whole log (stage 2)."""
    from scipy.signal import correlate

    valid = pm.valid
    period = float(np.median(pm.t1 - pm.t0))
    shift = 0.5 * readout_s
    v_lo, v_hi = pm.t0[0] - shift, pm.t1[-1] - shift
    video_s, log_s = v_hi - v_lo, float(gyro_t[-1] - gyro_t[0])
    # the grid is at most MAX_GRID_SAMPLES long, so a long log coarsens it rather than the memory growing
    h = max(float(grid_s) if grid_s else min(MAX_GRID_S, period / 2.0), log_s / MAX_GRID_SAMPLES)
    if video_s > log_s:
        raise DurationMismatch(f"the video lasts {video_s:.2f} s but the gyro log only {log_s:.2f} s: the "
                               "log cannot contain the video (a log of another flight, or cut short?)")
    nv = int(math.floor(video_s / h)) + 1
    u = v_lo + np.arange(nv) * h
    k = np.clip(np.searchsorted(pm.t1 - shift, u, side="right"), 0, len(pm.t0) - 1)
    p = pm.rate[k]
    w = valid[k].astype(np.float64)
    p = np.where(w[:, None] > 0, p, 0.0)
    W = w.sum()
    p = (p - (w[:, None] * p).sum(axis=0) / W) * w[:, None]

    nl = int(math.floor(log_s / h)) + 1
    G = cumulative_rotation(gyro_t, gyro_rate)
    box = max(1, int(round(period / h)))
    g = _gyro_grid(gyro_t, G, float(gyro_t[0]), h, nl)
    g = _exp_filter(g, h, tau_s)
    if box > 1:             # the picture sees the mean rate over one frame interval
        kern = np.ones(box) / box
        g = np.stack([np.convolve(g[:, a], kern, mode="same") for a in range(3)], axis=1)
    if nl < nv:
        raise DurationMismatch(f"the video lasts {video_s:.2f} s but the gyro log only {log_s:.2f} s")
    C = np.empty((3, 3, nl - nv + 1))
    for i in range(3):
        for j in range(3):
            C[i, j] = correlate(g[:, j], p[:, i], mode="valid", method="fft")
    gm = np.stack([correlate(g[:, j], w, mode="valid", method="fft") for j in range(3)], axis=1) / W
    e2 = correlate((g**2).sum(axis=1), w, mode="valid", method="fft")
    energy = np.maximum(e2 - W * (gm**2).sum(axis=1), 0.0)
    norm = math.sqrt(float((p**2).sum())) * np.sqrt(energy)
    floor = 1e-9 * (float(norm.max()) if norm.size else 0.0)
    if not floor > 0:
        raise LogMismatch("gyro log: the rates never change over the video's length (a log without gyro "
                          "data, or all zeros)")
    # the log's rotation over each stretch as long as the video, against the picture's: a log that
    # barely turns anywhere cannot hold this video, and the correlation alone would only say "no match"
    gyro_rms, picture_rms = math.sqrt(float(energy.max()) / W), math.sqrt(float((p**2).sum()) / W)
    if gyro_rms < MIN_LOG_MOTION_RATIO * picture_rms:
        raise LogMismatch(f"gyro log: it turns at most {math.degrees(gyro_rms):.2g} °/s RMS over any "
                          f"stretch as long as the video, which turns {math.degrees(picture_rms):.2g} °/s: "
                          "too little gyro motion to find the video in it (a log recorded at rest, or "
                          "another flight's?)")
    mounts = np.stack(MOUNTS)
    curves = (np.einsum("mij,ijl->ml", mounts, C) / np.maximum(norm, floor)).astype(np.float32)
    curves[:, norm < floor] = 0.0
    best_per_mount = curves.max(axis=1)
    order = np.argsort(best_per_mount)[::-1]
    mi, m2 = int(order[0]), int(order[1])
    li = int(np.argmax(curves[mi]))
    rho = float(curves[mi, li])
    # elsewhere: any mount, lags further than one second (and five frame periods) from the peak
    reach = int(math.ceil(max(1.0, 5 * period) / h))
    far = np.abs(np.arange(curves.shape[1]) - li) > reach
    rho_far = float(curves[:, far].max()) if far.any() else -1.0
    frac = 0.0
    if 0 < li < curves.shape[1] - 1:
        y0, y1, y2 = (float(v) for v in curves[mi, li - 1:li + 2])
        den = y0 - 2 * y1 + y2
        frac = float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5)) if den < 0 else 0.0
    lags = (v_lo - float(gyro_t[0])) - np.arange(curves.shape[1]) * h
    offset = (v_lo - float(gyro_t[0])) - (li + frac) * h
    cs = CoarseSync(offset, mi, rho, float(best_per_mount[m2]), m2, rho_far, h, lags, curves)
    _check_significance(cs)
    return cs


def _check_significance(cs: CoarseSync) -> None:
    if cs.ncc < MIN_NCC:
        raise LogMismatch(f"gyro log: the video's rotation correlates with the log at best {cs.ncc:.2f} "
                          f"(need ≥ {MIN_NCC}): the log does not contain this video (another flight, or "
                          "a gyro not on the camera's frame)")
    if cs.residual_ratio < MIN_RESIDUAL_RATIO:
        raise LogMismatch(f"gyro log: two places fit the video about equally (correlation {cs.ncc:.3f} and "
                          f"{cs.ncc_elsewhere:.3f} more than a second apart: the second leaves only "
                          f"{cs.residual_ratio:.1f}× the unexplained rotation of the first, need ≥ "
                          f"{MIN_RESIDUAL_RATIO:g}×): the motion repeats, or the log does not contain the "
                          "video")


# ----------------------------------------------------------------------------------------------- fine
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


class _FineProblem:
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
    prob = _FineProblem(pm, gyro_t, gyro_rate, coarse.time_offset_s, tau_s, readout_s)
    x0 = prob.start(coarse.time_offset_s)
    fits = {i: prob.fit(x0, MOUNTS[i]) for i in mounts}
    mi = min(fits, key=lambda i: fits[i][1])
    M = MOUNTS[mi]
    x, cost = fits[mi]
    banded = np.sum(np.all(np.isfinite(pm.band_rotvec), axis=2), axis=1) >= 2
    readout_sigma = math.nan
    if fit_readout and banded.sum() >= 0.5 * len(banded):
        prob = _FineProblem(pm, gyro_t, gyro_rate, x[0], tau_s, readout_s, bands=True)
        x, _ = prob.fit(prob.start(x[0], x), M)
        sigma = prob.jackknife(x, M, blocks)
        readout, readout_sigma = float(x[8]), float(sigma[8])
    else:
        sigma = prob.jackknife(x, M, blocks)
        readout = readout_s
    whole = _FineProblem(pm, gyro_t, gyro_rate, x[0], tau_s, readout)
    R = so3_exp(x[1:4]) @ M
    res_rate = (whole.phi - whole.predicted(x[:8], M)) / whole.dts[:, None]
    return FineSync(float(x[0]), float(sigma[0]), 0.5 * tau_s, x[1:4].copy(), sigma[1:4].copy(),
                    x[4:7].copy(), sigma[4:7].copy(), R, mi, float(np.sqrt(np.mean(res_rate**2))),
                    float(np.sqrt(np.mean((whole.phi / whole.dts[:, None]) ** 2))), len(whole.phi), cost,
                    {int(i): c for i, (_, c) in fits.items()}, readout, readout_sigma,
                    float(x[7] * 1e6) if whole.fit_drift else 0.0,
                    float(sigma[7] * 1e6) if whole.fit_drift else math.nan, whole.t_mid)


# --------------------------------------------------------------------------------------------- result
@dataclass
class SyncResult:
    """What `synchronise` found. Conventions as the calibration's (docs/design.md §2):
    ω_cam = R_cam_gyro (ω_gyro − bias), t_cam = t_gyro + time_offset_s.

    The mount's margin is given twice: the correlation of the best mount over the runner-up's
    (`CoarseSync.mount_margin`), and the ratio of the runner-up's fit cost to the chosen one's
    (`mount_cost_ratio`; inf when only one mount came close enough to be fitted)."""

    coarse: CoarseSync
    fine: FineSync
    motion: dict
    picture: PictureMotion
    seconds: dict = field(default_factory=dict)
    tau_s: float = 0.0              # as given (the sync does not fit it)
    readout_given_s: float = 0.0    # as given; the fitted value is `fine.readout_s`
    frames: tuple[int, int] | None = None   # the frames [i0, i1) the log covers, when not all of them

    @property
    def time_offset_s(self) -> float:
        return self.fine.time_offset_s

    @property
    def mount_index(self) -> int:
        return self.fine.mount_index

    @property
    def mount(self) -> np.ndarray:
        return MOUNTS[self.fine.mount_index]

    @property
    def R_cam_gyro(self) -> np.ndarray:
        return self.fine.R_cam_gyro

    @property
    def mount_cost_ratio(self) -> float:
        others = [c for i, c in self.fine.mount_costs.items() if i != self.fine.mount_index]
        return min(others) / self.fine.cost if others and self.fine.cost > 0 else math.inf

    def camera_clock(self, gyro_t) -> np.ndarray:
        """Gyro sample times moved onto the video clock by the offset (t + time_offset_s): a recording's
        `/gyro/t`, whose calibration then needs `time_offset_s` = 0 (`calibration_changes`; its range is
        ±1 s) and carries the drift about the video's middle (`clock_drift_ppm`, `clock_epoch_s`)."""
        return np.asarray(gyro_t, np.float64) + self.fine.time_offset_s

    def calibration_changes(self) -> dict:
        """Keyword arguments for `Calibration.replace`: the synced gyro chain, for gyro times already
        on the video clock (`camera_clock`)."""
        period = float(np.median(self.picture.t1 - self.picture.t0))
        return {"time_offset_s": 0.0,
                "R_cam_gyro": tuple(tuple(float(v) for v in row) for row in self.fine.R_cam_gyro),
                "bias_rad_s": tuple(float(v) for v in self.fine.bias_rad_s),
                "readout_s": min(float(self.fine.readout_s), 0.99 * period),
                "clock_drift_ppm": float(self.fine.clock_drift_ppm),
                "clock_epoch_s": float(self.fine.clock_epoch_video_s)}

    def to_dict(self) -> dict:
        c, f = self.coarse, self.fine
        ratio = self.mount_cost_ratio
        return {
            "time_offset_s": {"value": f.time_offset_s, "sigma": f.time_offset_sigma_s,
                              "lag_bound": f.lag_bound_s},
            "coarse_time_offset_s": c.time_offset_s,
            "mount": self.mount.astype(int).tolist(),
            "mount_index": f.mount_index,
            "frames_covered": list(self.frames) if self.frames is not None else None,
            "ncc": c.ncc, "ncc_second_mount": c.ncc_second_mount,
            "second_mount": MOUNTS[c.second_mount_index].astype(int).tolist(),
            "mount_margin_ncc": c.mount_margin,
            "mount_cost_ratio": ratio if math.isfinite(ratio) else None,
            "ncc_elsewhere": c.ncc_elsewhere,
            "misalignment_rad": {"value": f.misalignment_rad.tolist(),
                                 "sigma": f.misalignment_sigma_rad.tolist()},
            "R_cam_gyro": f.R_cam_gyro.tolist(),
            "gyro_bias_rad_s": {"value": f.bias_rad_s.tolist(), "sigma": f.bias_sigma_rad_s.tolist()},
            "clock_drift_ppm": {"value": f.clock_drift_ppm, "epoch_video_s": f.clock_epoch_video_s,
                                "sigma": (f.clock_drift_sigma_ppm if math.isfinite(f.clock_drift_sigma_ppm)
                                          else None)},
            "readout_s": {"value": f.readout_s,
                          "sigma": f.readout_sigma_s if math.isfinite(f.readout_sigma_s) else None},
            "tau_s": {"value": self.tau_s, "sigma": None, "note": "as given; see sync_discrepancy"},
            "residual_rms_rad_s": f.residual_rms_rad_s, "picture_rms_rad_s": f.picture_rms_rad_s,
            "intervals": f.n_intervals, "motion": self.motion, "grid_s": c.grid_s,
            "uncertainty": "sigma: delete-one-block jackknife over 8 contiguous stretches of the video; "
                           "lag_bound: the offset's systematic bound from the picture's apparent lag (tau/2)",
            "seconds": self.seconds,
        }


def synchronise(frames, frame_t, gyro_t, gyro_rate, intrinsics: Intrinsics, *, tau_s: float = 0.0,
                readout_s: float = 0.0, work_width: int = 160, smooth_px: float = 1.5,
                progress=None) -> SyncResult:
    """Find where a video sits in a gyro log and how the camera is mounted (module docstring).

    frames [N, H, W] grey (8- or 16-bit, AGC allowed); frame_t [N] s on the video clock (a frame's
    time: its last row read); gyro_t [M] s on the log clock; gyro_rate [M, 3] rad/s in the flight
    controller's frame; `intrinsics` of the frames; `tau_s` and `readout_s` as far as known (0: none).
    `frames` may also be any sequence of [H, W] frames with len() and indexing (a lazy reader: one
    frame is read at a time). Raises a `SyncError` subclass naming what was wrong."""
    lazy = hasattr(frames, "__len__") and hasattr(frames, "__getitem__")
    if not isinstance(frames, np.ndarray) and not lazy:
        frames = np.asarray(frames)
    n = len(frames)
    shape = (n, *np.shape(frames[0])) if n else np.shape(frames)
    if len(shape) != 3 or shape[1] < 16 or shape[2] < 16:
        raise SyncInputError(f"frames: expected [N, H, W] grey frames of ≥ 16×16 px, got shape {shape}")
    if (shape[2], shape[1]) != (intrinsics.width, intrinsics.height):
        raise SyncInputError(f"frames: {shape[2]}×{shape[1]} px but the intrinsics describe "
                             f"{intrinsics.width}×{intrinsics.height}")
    if not (0 <= tau_s <= 1 and 0 <= readout_s <= 1):
        raise SyncInputError(f"tau_s {tau_s!r}, readout_s {readout_s!r}: expected 0–1 s")
    t, gt, gr = _check_arrays(frame_t, gyro_t, gyro_rate, len(frames))
    clock = time.perf_counter
    t0 = clock()
    pm = picture_motion(frames, t, intrinsics, work_width=work_width, smooth_px=smooth_px, progress=progress)
    t1 = clock()
    stats = check_motion(pm)
    part = None
    try:
        coarse = coarse_sync(pm, gt, gr, tau_s=tau_s, readout_s=readout_s)
    except (DurationMismatch, LogMismatch):
        part = covered_part(pm, gt, gr, tau_s=tau_s, readout_s=readout_s)
        if part is None:
            raise
        pm = pm.sliced(*part)
        coarse = coarse_sync(pm, gt, gr, tau_s=tau_s, readout_s=readout_s)
    t2 = clock()
    fine = refine(pm, gt, gr, coarse, tau_s=tau_s, readout_s=readout_s)
    t3 = clock()
    return SyncResult(coarse, fine, stats, pm, {"picture": t1 - t0, "coarse": t2 - t1, "fine": t3 - t2},
                      tau_s, readout_s, part)


def covered_part(pm: PictureMotion, gyro_t, gyro_rate, *, tau_s: float = 0.0,
                 readout_s: float = 0.0) -> tuple[int, int] | None:
    """The frames [i0, i1) of a video that a log covers when it does not cover all of them (a flight
    controller that logs only while armed, a video running from power-up), or None.

    Parts of the video, as long as the log allows and then `PART_SHRINK` times shorter down to
    `MIN_PART_S` and `MIN_PART_FRACTION` of the video, are placed in the log by `coarse_sync` (each
    with its own significance tests); the longest length at which one is found wins, the best
    correlation among its parts. The frames whose comet tails (8 τ) and read times lie in the log
    with `PART_MARGIN_S` to spare, around the placed part, are the covered ones."""
    n = len(pm.t0) + 1
    t = np.r_[pm.t0, pm.t1[-1]]
    period = float(np.median(pm.t1 - pm.t0))
    log_s = float(gyro_t[-1] - gyro_t[0])
    length = min(n, int(log_s / period))
    shortest = max(int(math.ceil(MIN_PART_S / period)), int(math.ceil(MIN_PART_FRACTION * n)),
                   MIN_INTERVALS + 1)
    while length >= shortest:
        step = max(1, length // 4)
        found = []
        for i0 in sorted({*range(0, n - length + 1, step), n - length}):
            try:
                cs = coarse_sync(pm.sliced(i0, i0 + length), gyro_t, gyro_rate, tau_s=tau_s,
                                 readout_s=readout_s)
            except SyncError:
                continue
            found.append((cs.ncc, cs.time_offset_s))
        if found:
            offset = max(found)[1]
            t_log = t - offset                      # t_cam = t_gyro + offset
            reach = 8.0 * tau_s + readout_s + PART_MARGIN_S
            inside = np.flatnonzero((t_log - reach >= gyro_t[0]) & (t_log + PART_MARGIN_S <= gyro_t[-1]))
            if len(inside) < shortest:
                return None
            return int(inside[0]), int(inside[-1]) + 1
        length = int(length * PART_SHRINK)
    return None


# --------------------------------------------------------------------------------------------- figure
def plot_sync(result: SyncResult, gyro_t, gyro_rate, path) -> None:
    """PNG: the picture's rotation rate against the gyro's, per camera axis, before sync (the log as
    recorded, its first sample at the first frame) and after (rotated into the camera frame by
    R_cam_gyro, bias removed, shifted by the offset, through τ and averaged over each frame interval
    as the picture sees it); below, the correlation over the log for the chosen and the runner-up
    mount."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = np.asarray(gyro_t, np.float64)
    gr = np.asarray(gyro_rate, np.float64)
    pm, fine, coarse = result.picture, result.fine, result.coarse
    naive_offset = float(pm.t0[0] - gt[0])
    after = _FineProblem(pm, gt, gr, fine.time_offset_s, result.tau_s, fine.readout_s)
    x_after = np.r_[fine.time_offset_s, fine.misalignment_rad, fine.bias_rad_s, 1e-6 * fine.clock_drift_ppm]
    rate_after = after.predicted(x_after, MOUNTS[fine.mount_index]) / after.dts[:, None]
    before = _FineProblem(pm, gt, gr, naive_offset, 0.0, 0.0)
    rate_before = before.predicted(np.r_[naive_offset, np.zeros(7)], np.eye(3)) / before.dts[:, None]
    tm = 0.5 * (after.t0 + after.t1) - pm.t0[0]
    pic = after.phi / after.dts[:, None]
    fig = plt.figure(figsize=(12, 9), constrained_layout=True)
    grid = fig.add_gridspec(4, 2)
    deg = 180.0 / math.pi
    for col, (label, g) in enumerate((("before sync (log as recorded, same start)", rate_before),
                                      (f"after sync (offset {fine.time_offset_s:.4f} s, mount "
                                       f"{MOUNTS[fine.mount_index].astype(int).tolist()})", rate_after))):
        for a, name in enumerate(("x (right)", "y (down)", "z (forward)")):
            ax = fig.add_subplot(grid[a, col])
            ax.plot(tm, pic[:, a] * deg, ".-", ms=3, lw=0.8, label="picture")
            ax.plot(tm, g[:, a] * deg, lw=1.0, label="gyro")
            ax.set_ylabel(f"ω {name} (°/s)")
            if a == 0:
                ax.set_title(label, fontsize=10)
                ax.legend(loc="upper right", fontsize=8)
            if a == 2:
                ax.set_xlabel("video time (s)")
    ax = fig.add_subplot(grid[3, :])
    ax.plot(coarse.lags_s, coarse.ncc_curves[fine.mount_index], lw=0.8, label=f"mount {fine.mount_index}")
    ax.plot(coarse.lags_s, coarse.ncc_curves[coarse.second_mount_index], lw=0.8, alpha=0.7,
            label=f"runner-up mount {coarse.second_mount_index}")
    ax.axvline(fine.time_offset_s, color="k", lw=0.6, ls="--")
    ax.set_xlabel("time offset t_cam − t_gyro (s)")
    ax.set_ylabel("normalised correlation")
    ax.set_title(f"whole-log correlation: peak {coarse.ncc:.3f}, elsewhere {coarse.ncc_elsewhere:.3f}, "
                 f"runner-up mount {coarse.ncc_second_mount:.3f}", fontsize=10)
    ax.legend(loc="lower right", fontsize=8)
    fig.savefig(path, dpi=90)
    plt.close(fig)
