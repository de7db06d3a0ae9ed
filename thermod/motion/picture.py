"""The camera's rotation between consecutive frames, measured from the pictures alone.

Each frame is normalised on its own to zero median and unit 1–99 % spread, which removes an automatic
gain control's per-frame gain and offset whenever it is a global affine map of the counts; then it is
shrunk to a working width (≈ 160 px) and mapped to 8 bits. Shi–Tomasi corners of frame k−1 are tracked
into frame k by pyramidal Lucas–Kanade, kept when the backward track returns within 0.5 px, and turned
into rays v = K⁻¹p/‖K⁻¹p‖. The rotation between the frames, Q = R(t_{k−1})ᵀ R(t_k) with
v_{k−1} = Q v_k (docs/design.md §2), is the orthogonal Procrustes (Kabsch) fit on the rays inside a
two-point RANSAC; its rotation vector φ_k ≈ ∫ω dt over the interval, in the camera frame, with the
information matrix Σ [v]×ᵀ[v]× / σ² from the fit's residual σ (rad). The same fit on three horizontal
bands of the frame alone carries the rolling readout (`PictureMotion`).

The picture lags the true rotation through the detector: a comet-tailed corner is tracked at its
sharper head more than at its centroid, so the measured lag is shorter than τ. A video whose rotation
does not rise above its own measurement noise is refused (`TooLittleMotion`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from thermod.errors import ThermodError
from thermod.physics.geometry import Intrinsics, so3_log

MIN_INTERVALS = 20            # picture intervals with a rotation estimate a sync needs
MIN_FEATURES = 8              # tracked corners a rotation estimate needs
BANDS = 3                     # horizontal bands of a frame fitted apart (rolling readout)
MIN_MOTION_SNR = 5.0          # picture rotation RMS over its measurement noise RMS
MIN_MOTION_PX = 0.25          # picture rotation RMS per interval, in working-image pixels


class MotionError(ThermodError):
    """The pictures' motion could not be measured; the message says what was wrong."""


class TooLittleMotion(MotionError):
    """The video's rotation does not rise above the noise of its own measurement."""


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
