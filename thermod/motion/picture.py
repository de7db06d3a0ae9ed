"""The camera's rotation between consecutive frames, measured from the pictures alone.

Each frame is normalised on its own to zero median and unit 1–99 % spread, which removes an automatic
gain control's per-frame gain and offset whenever it is a global affine map of the counts; then it is
shrunk to a working width (≈ 160 px) and mapped to 8 bits. Shi–Tomasi corners of frame k−1 are tracked
into frame k by pyramidal Lucas–Kanade, kept when the backward track returns within 0.5 px, and turned
into rays v = K⁻¹p/‖K⁻¹p‖. The rotation between the frames, Q = R(t_{k−1})ᵀ R(t_k) with
v_{k−1} = Q v_k (docs/design.md §2), is the orthogonal Procrustes (Kabsch) fit on the rays inside a
two-point RANSAC; its rotation vector φ_k ≈ ∫ω dt over the interval, in the camera frame, with the
information matrix Σ [v]×ᵀ[v]× / σ² from the fit's residual σ (rad). The same fit on three horizontal
bands of the frame alone carries the rolling readout (`PictureMotion`). Where the corners do not agree
(too little texture, heavy smear), `PairRegistrar.measure_dense` registers every pixel instead (ECC).

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
MIN_WORK_SIDE = 8             # px per side of the working image (a frame shrunk to the working width)
BANDS = 3                     # horizontal bands of a frame fitted apart (rolling readout)
MIN_MOTION_SNR = 5.0          # picture rotation RMS over its measurement noise RMS
MIN_MOTION_PX = 0.25          # picture rotation RMS per interval, in working-image pixels
# a dense fit's error per pair, working px: 0.4–1 px measured where the corners failed (the simulated
# payload's low-texture turns at 80 °/s, 10 working px a frame); its information is one such point's
DENSE_SIGMA_PX = 1.0
DENSE_ITERATIONS = 10         # ECC's steps at most (~1 ms each at 160×120; 40 moved its result ≤ 0.1 px)
DENSE_GRID = 10               # working px between the points its homography is fitted by a rotation at


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


def normalise_frame(frame: np.ndarray, exclude: np.ndarray | None = None) -> np.ndarray:
    """A frame's counts → float32 with median 0 and 1–99 % spread 1: a per-frame affine gain and
    offset (an AGC) drops out. `exclude` (bool, the frame's shape): pixels left out of the
    percentiles (a static overlay, whose bright strokes would otherwise set the 99 % level)."""
    f = np.asarray(frame, dtype=np.float32)
    use = f if exclude is None or exclude.shape != f.shape or exclude.all() else f[~exclude]
    lo, med, hi = np.percentile(use, (1.0, 50.0, 99.0))
    spread = float(hi - lo)
    if not spread > 0:
        spread = float(np.std(f)) or 1.0
    return (f - np.float32(med)) / np.float32(spread)


U8_PER_UNIT = 160.0           # working-image codes per unit of the normalised scale (1–99 % spread 1)


def _to_u8(z: np.ndarray) -> np.ndarray:
    return np.clip(128.0 + U8_PER_UNIT * z, 0, 255).astype(np.uint8)


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
    d = prev_rays[None] - np.matmul(next_rays[None], np.transpose(Qs, (0, 2, 1)))
    err = np.sqrt(np.sum(d * d, axis=2))
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


@dataclass
class PairFit:
    """The rotation between two working frames: `rotvec` (rad, camera frame, Q = R(t0)ᵀ R(t1)), its
    information matrix `info` (rad⁻²), the inlier corners' count and residual (working px), and per band
    of rows the same fit (NaN / zeros where a band has too few) with the band's mean lead (share of the
    readout its corners are read before the frame time)."""

    rotvec: np.ndarray
    info: np.ndarray
    n_features: int
    residual_px: float
    band_rotvec: np.ndarray
    band_info: np.ndarray
    band_lead: np.ndarray
    lead: float            # the inliers' mean lead (the whole-frame fit's)

    @property
    def noise_rad(self) -> float:
        """RMS error of the rotation estimate (rad)."""
        return math.sqrt(np.trace(np.linalg.inv(self.info)) / 3.0)


class PairRegistrar:
    """Registers consecutive frames (module docstring): `prepare` turns a frame into its 8-bit working
    image, `measure` fits the rotation between two of them. `resize_first`: shrink before normalising
    (the percentiles of the working image, not of the full frame: cheaper, for a live stream)."""

    def __init__(self, intrinsics: Intrinsics, *, work_width: int = 160, max_features: int = 150,
                 seed: int = 0, smooth_px: float = 0.0, resize_first: bool = False, lk_levels: int = 3,
                 lk_window: int = 15):
        import cv2

        self.full = intrinsics
        self.work, self.scale = _work_intrinsics(intrinsics, work_width)
        if min(self.work.width, self.work.height) < MIN_WORK_SIDE:
            raise MotionError(f"{intrinsics.width}×{intrinsics.height} px frames are {self.work.width}×"
                              f"{self.work.height} px at the tracker's working width: expected ≥ "
                              f"{MIN_WORK_SIDE} px per side (a strip this thin cannot be tracked)")
        self.K_inv = self.work.K_inv
        self.f_px = math.sqrt(self.work.fx * self.work.fy)
        self.rng = np.random.default_rng(seed)
        self.size = (self.work.width, self.work.height)
        self.border = np.zeros((self.work.height, self.work.width), np.uint8)
        self.edge = max(3, self.work.width // 40)
        self.border[self.edge:-self.edge, self.edge:-self.edge] = 1
        self.max_features, self.smooth_px, self.resize_first = max_features, smooth_px, resize_first
        self.lk = {"winSize": (int(lk_window), int(lk_window)), "maxLevel": int(lk_levels),
                   "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}

    def prepare(self, frame, exclude: np.ndarray | None = None) -> np.ndarray:
        """The frame's working image (8 bits, normalised on its own: an AGC drops out). `exclude`
        (bool, working size): a static overlay, left out of the normalisation."""
        import cv2

        if self.resize_first and self.scale != 1.0:
            f = np.asarray(frame)
            if f.dtype not in (np.uint8, np.uint16, np.float32):   # what cv2 shrinks as it is
                f = f.astype(np.float32)
            z = normalise_frame(cv2.resize(f, self.size, interpolation=cv2.INTER_AREA), exclude)
        else:
            z = normalise_frame(frame, exclude)
            if self.scale != 1.0:
                z = cv2.resize(z, self.size, interpolation=cv2.INTER_AREA)
        if self.smooth_px > 0:
            z = cv2.GaussianBlur(z, (0, 0), self.smooth_px)
            z = z / max(float(np.percentile(z, 99) - np.percentile(z, 1)), 1e-6)
        return _to_u8(z)

    def measure(self, prev: np.ndarray, cur: np.ndarray, *, bands: bool = True,
                predicted: np.ndarray | None = None, exclude: np.ndarray | None = None) -> PairFit | None:
        """The rotation from working image `prev` to `cur`, or None with too few corners agreeing;
        `bands` False leaves the band fits out (NaN). `predicted`: a rotation vector expected for the pair
        (e.g. the last one's), from which the corners' tracks start, both ways: a fast, smeared pair
        then needs only the change of motion tracked. `exclude`: working pixels where no corner is
        taken (a static overlay)."""
        import cv2

        where = self.border if exclude is None else self.border & ~exclude.astype(bool)
        p0 = cv2.goodFeaturesToTrack(prev, self.max_features, 0.005, self.edge, mask=where.astype(np.uint8),
                                     blockSize=5)
        if p0 is None or len(p0) < MIN_FEATURES:
            return None
        lk, guess = self.lk, None
        if (H := self._homography(predicted)) is not None:
            guess = cv2.perspectiveTransform(p0.astype(np.float64), H).astype(np.float32)
            lk = {**self.lk, "flags": cv2.OPTFLOW_USE_INITIAL_FLOW}
        p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, guess.copy() if guess is not None else None, **lk)
        pb, stb, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy() if guess is not None else None, **lk)
        ok = (st[:, 0] == 1) & (stb[:, 0] == 1) & (np.linalg.norm((pb - p0)[:, 0], axis=1) < 0.5)
        a, b = p0[ok, 0].astype(np.float64), p1[ok, 0].astype(np.float64)
        if not len(a):
            return None
        ra, rb = _rays(a, self.K_inv), _rays(b, self.K_inv)
        fit = fit_rotation(ra, rb, self.f_px, self.rng)
        if fit is None:
            return None
        Q, mask, sigma = fit
        ra, rb = ra[mask], rb[mask]
        brot = np.full((BANDS, 3), np.nan)
        binfo = np.zeros((BANDS, 3, 3))
        blead = np.full(BANDS, np.nan)
        band = np.minimum((b[mask, 1] / self.work.height * BANDS).astype(int), BANDS - 1)
        row_full = (b[mask, 1] + 0.5) / self.scale - 0.5         # working row → full-frame row
        lead = 1.0 - (row_full + 1.0) / self.full.height
        for j in range(BANDS if bands else 0):
            sel = band == j
            if sel.sum() >= MIN_FEATURES:
                brot[j] = so3_log(_kabsch(ra[sel], rb[sel]))
                binfo[j] = _information(rb[sel], sigma)
                blead[j] = float(np.mean(lead[sel]))
        return PairFit(so3_log(Q), _information(rb, sigma), int(mask.sum()), sigma * self.f_px, brot, binfo,
                       blead, float(np.mean(lead)))

    def _homography(self, rotvec: np.ndarray | None) -> np.ndarray | None:
        """Where a working pixel of the first frame lies in the second after the rotation `rotvec`
        (v_prev = Q v_cur: p ↦ K Qᵀ K⁻¹ p), or None without a finite one."""
        if rotvec is None or not np.all(np.isfinite(rotvec)):
            return None
        from thermod.physics.geometry import so3_exp

        return self.work.K @ so3_exp(rotvec).T @ self.K_inv

    def measure_dense(self, prev: np.ndarray, cur: np.ndarray, *, predicted: np.ndarray | None = None,
                      exclude: np.ndarray | None = None) -> PairFit | None:
        """The rotation from `prev` to `cur` by dense registration, for a pair whose corners do not
        agree (too little texture, heavy smear): ECC on a homography (Evangelidis & Psarakis 2008),
        started from `predicted`, over every pixel but `exclude`, then the rotation that moves a grid of
        points as the homography does (Kabsch). No bands; `info` is one point's of σ = `DENSE_SIGMA_PX`
        at the grid's rays. None when ECC does not converge."""
        import cv2

        H0 = self._homography(predicted)
        H0 = np.eye(3) if H0 is None else H0
        keep = None if exclude is None else (~exclude.astype(bool)).astype(np.uint8)
        try:
            stop = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, DENSE_ITERATIONS, 1e-4)
            W0 = (H0 / H0[2, 2]).astype(np.float32)
            _, W = cv2.findTransformECC(prev.astype(np.float32), cur.astype(np.float32), W0,
                                        cv2.MOTION_HOMOGRAPHY, stop, keep, 5)
        except cv2.error:          # no convergence: a flat or uncorrelated pair
            return None
        ys, xs = np.mgrid[self.edge:self.work.height - self.edge:DENSE_GRID,
                          self.edge:self.work.width - self.edge:DENSE_GRID]
        a = np.c_[xs.ravel(), ys.ravel()].astype(np.float64)
        b = np.c_[a, np.ones(len(a))] @ W.astype(np.float64).T      # x of prev lies at W x in cur
        if len(a) < 3 or not np.all(np.abs(b[:, 2]) > 1e-6):      # a strip without a grid; a warp to infinity
            return None
        b = b[:, :2] / b[:, 2:]
        ra, rb = _rays(a, self.K_inv), _rays(b, self.K_inv)
        sigma = DENSE_SIGMA_PX / self.f_px
        lead = 1.0 - ((b[:, 1] + 0.5) / self.scale + 0.5) / self.full.height
        return PairFit(so3_log(_kabsch(ra, rb)), _information(rb, sigma) / len(rb), 0, DENSE_SIGMA_PX,
                       np.full((BANDS, 3), np.nan), np.zeros((BANDS, 3, 3)), np.full(BANDS, np.nan),
                       float(np.mean(lead)))


def picture_motion(frames, frame_t, intrinsics: Intrinsics, *, work_width: int = 160,
                   max_features: int = 150, seed: int = 0, smooth_px: float = 0.0,
                   progress=None) -> PictureMotion:
    """The camera rotation between consecutive frames (module docstring, stage 1).

    `frames` [N, H, W] grey, or a sequence of [H, W] frames (any integer or float type: each frame is
    normalised on its own, and read once);
    `frame_t` [N] seconds on the video clock; `intrinsics` of the full frame."""
    t = np.asarray(frame_t, dtype=np.float64)
    n = len(frames)
    reg = PairRegistrar(intrinsics, work_width=work_width, max_features=max_features, seed=seed,
                        smooth_px=smooth_px)
    rotvec = np.full((n - 1, 3), np.nan)
    info = np.zeros((n - 1, 3, 3))
    nfeat = np.zeros(n - 1, dtype=np.int64)
    resid = np.full(n - 1, np.nan)
    brot = np.full((n - 1, BANDS, 3), np.nan)
    binfo = np.zeros((n - 1, BANDS, 3, 3))
    blead = np.full((n - 1, BANDS), np.nan)
    prev = reg.prepare(frames[0])
    for k in range(1, n):
        cur = reg.prepare(frames[k])
        fit = reg.measure(prev, cur)
        if fit is None:         # corners that disagree: every pixel, from the last pair's rotation
            fit = reg.measure_dense(prev, cur, predicted=rotvec[k - 2] if k >= 2 else None)
        if fit is not None:
            rotvec[k - 1], info[k - 1], nfeat[k - 1], resid[k - 1] = fit.rotvec, fit.info, fit.n_features, \
                fit.residual_px
            brot[k - 1], binfo[k - 1], blead[k - 1] = fit.band_rotvec, fit.band_info, fit.band_lead
        prev = cur
        if progress is not None:
            progress(k, n - 1)
    return PictureMotion(t[:-1].copy(), t[1:].copy(), rotvec, info, nfeat, resid, reg.work, brot, binfo,
                         blead)


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
