"""The camera's rotation track from the pictures alone: a gyro for a video that has none.

`estimate_track(frames, frame_t, intrinsics, tau_s=…, readout_s=…)` measures the rotation between
consecutive frames with the sync's picture motion (`thermod.motion.picture`: per-frame normalisation
against an AGC; KLT corners; Kabsch in a two-point RANSAC against moving objects and parallax) after
handling what a video brings that a gyro does not: static overlays are found (`static_overlay`) and
inpainted; duplicated frames are left out (`duplicates`); cuts, textureless frames, fits far from
their neighbours and time gaps (lost frames, `GAP_PERIODS`) leave a hole, never invented motion
(frames over `MAX_PERIOD_S` apart are refused); the blur's lag (τ, the exponential's centroid,
Eq. 11, plus each band's share of the readout) shifts each measurement's time. A cubic spline of
the cumulative rotation through each stretch without holes is the track; its derivative, sampled at
`rate_hz`, is the camera-frame gyro with a σ per sample (`RotationTrack.gyro`). The rules in full:
docs/design.md §3, "Importing a video without a gyro".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from thermod.motion.picture import MotionError, normalise_frame, picture_motion
from thermod.physics.geometry import Intrinsics

MIN_FRAMES = 4               # a track needs this many frames (three intervals, a cubic)
MIN_MEASURED_FRACTION = 0.5  # ... and a rotation measured between this share of consecutive frames
DUPLICATE_RATIO = 0.02       # median |Δ| of a duplicate over the video's median |Δ| (codec noise only)
DUPLICATE_ABS = 0.004        # ... and at most this on the normalised (1–99 % spread 1) scale
MIN_REGISTERED_NCC = 0.5     # frames registered by the fitted rotation must correlate this well
OVERLAY_STILL_SHARE = 0.2    # an overlay pixel's change over gradient is < this × the textured median ...
OVERLAY_MOVING_RATIO = 0.1   # ... which must show motion (≥ this: ~0.1 working px per frame; a still
                             # camera leaves only the codec's noise)
OVERLAY_MAX_FRACTION = 0.25  # a "static" share above this is a still camera, not an overlay
OVERLAY_DILATE_PX = 2        # working pixels added around an overlay (its anti-aliased edge)
DEFAULT_RATE_HZ = 1000.0
OUTLIER_K = 8.0              # an interval's rate misses its neighbours' prediction by > this × the median
OUTLIER_MIN_RAD_S = math.radians(45.0)   # ... and by more than this
BAND_SMOOTHING = 1e-3        # the banded fit's second-difference penalty, relative to the median weight
SMOOTH_MIN_KNOTS = 6         # `gyro(smooth=True)`: stretches of fewer frames are interpolated
GAP_PERIODS = 4.0            # an interval over this × the median frame interval: frames lost or a time jump
MAX_PERIOD_S = 2.0           # a median frame interval over this: no rate during a frame can be told (and the
                             # gyro, sampled at rate_hz across every interval, would grow with it unbounded)
HOLE_PERIODS = 6             # samples left out before a stretch that follows an unknown interval (a
                             # hole is > thermod.restore.policy.MAX_STEP_PERIODS periods)
WORK_WIDTH = 160             # the picture motion's working width
SMOOTH_PX = 1.5              # the tracker's smoothing: it sees more of a comet's tail than its head

STATUS = ("ok", "duplicate", "untracked", "cut", "gap")


class TrackError(MotionError):
    """A video from which no rotation track can be estimated; the message says why."""


@dataclass
class RotationTrack:
    """The camera's rotation from the pictures (module docstring).

    `frame_t` [N] the video's frame times; `rotvec` [N−1, 3] the rotation vector of each interval
    (camera frame, rad; NaN where unknown), `sigma_rad` [N−1] its RMS error; `status` [N−1] one of
    `STATUS` per interval: "duplicate" (frame k+1 repeats frame k: the rotation across it is split by
    time), "untracked" (too few corners: textureless or changed beyond tracking), "cut" (a fit the
    pictures do not confirm), "gap" (over `GAP_PERIODS` frame intervals long: frames were lost or the
    clock jumped, so only the net rotation across it could be seen). `lag_s`: the registered
    positions' lag behind the read times.
    `overlay`: the static overlay found (working-resolution mask) or None."""

    frame_t: np.ndarray
    rotvec: np.ndarray
    sigma_rad: np.ndarray
    status: np.ndarray
    lag_s: float
    overlay: np.ndarray | None
    work_scale: float
    ncc: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # rolling readout: the band rotations (thermod.motion.picture.BANDS) between frames a < b, each placed
    # at its own lag (τ + the band's mean lead × readout); empty without a readout
    bands: dict = field(default_factory=dict)

    @property
    def known(self) -> np.ndarray:
        return np.all(np.isfinite(self.rotvec), axis=1)

    def flagged(self) -> dict[str, list[int]]:
        """Frame indices by flag: "duplicate" (frame repeats its predecessor), "cut", "untracked" and
        "gap" (the motion into the frame is unknown)."""
        return {s: [int(k) + 1 for k in np.flatnonzero(self.status == s)] for s in STATUS[1:]}

    def rate_at_frames(self) -> np.ndarray:
        """Mean rate over each interval (rad/s, NaN where unknown)."""
        return self.rotvec / np.diff(self.frame_t)[:, None]

    def gyro(self, rate_hz: float = DEFAULT_RATE_HZ, lead_s: float = 0.0, tail_s: float = 0.0,
             smooth: bool = False):
        """(t [M], rate [M, 3] rad/s camera frame, sigma [M] rad/s): the spline's derivative sampled at
        `rate_hz` on the video clock over each stretch of known intervals, shifted by the lag. The rate
        is held `lead_s` before the first frame of the video (its kernel window) and `tail_s` after each
        stretch's last knot (which lies `lag_s` before its frame's read time), but never into the
        `HOLE_PERIODS` samples before the next stretch: no samples inside an unknown interval.
        `smooth`: a smoothing spline through the measured angles instead of the interpolating one
        (`_smoothed_rate`), for τ's fit, which the rate's noise biases; the kernels take the
        interpolated rate (the one benchmarks/results/video_motion.md measured). A rolling readout's
        banded fit is penalised already and is the same either way."""
        h = 1.0 / rate_hz
        known = self.known
        stretches = []
        k, n = 0, len(known)
        while k < n:
            if not known[k]:
                k += 1
                continue
            j = k
            while j < n and known[j]:
                j += 1
            stretches.append((k, j))            # intervals k … j−1: frames k … j
            k = j
        out = []
        for i, (k, j) in enumerate(stretches):
            t, w, s = self._stretch(k, j, h, lead_s if k == 0 else 0.0, tail_s, smooth)
            if i + 1 < len(stretches):
                nxt = self.frame_t[stretches[i + 1][0]] - self.lag_s
                keep = t < nxt - HOLE_PERIODS * h
                t, w, s = t[keep], w[keep], s[keep]
            out.append((t, w, s))
        if not out:
            return np.zeros(0), np.zeros((0, 3)), np.zeros(0)
        return tuple(np.concatenate([o[i] for o in out]) for i in range(3))

    def _stretch(self, k: int, j: int, h: float, lead_s: float, tail_s: float, smooth: bool = False):
        from scipy.interpolate import CubicSpline

        knots = self.frame_t[k:j + 1] - self.lag_s
        rate, dom = None, (knots[0], knots[-1])
        if self.bands:
            rate, dom = self._banded_rate(self.frame_t[k], self.frame_t[j])
        if rate is None:
            theta = np.r_[np.zeros((1, 3)), np.cumsum(self.rotvec[k:j], axis=0)]
            if smooth and len(knots) >= SMOOTH_MIN_KNOTS and np.any(self.sigma_rad[k:j] > 0):
                rate = _smoothed_rate(knots, theta)
            else:
                # exact angles, or too few to smooth: not-a-knot from 4 knots (a cubic through four
                # points is exact), the natural spline below
                rate = CubicSpline(knots, theta, bc_type="not-a-knot" if len(knots) >= 4 else "natural"
                                   ).derivative()
            dom = (knots[0], knots[-1])
        lo, hi = knots[0] - lead_s, knots[-1] + tail_s
        t = lo + h * np.arange(int(math.floor((hi - lo) / h)) + 1)
        w = rate(np.clip(t, *dom))            # held beyond the ends
        idx = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, j - k - 1)
        sig = self.sigma_rad[k:j][idx] / np.diff(knots)[idx]
        return t, w, sig

    def _banded_rate(self, ta: float, tb: float):
        """The rate of a stretch from its band rotations, each at its own time (rolling readout):
        θ(t) a cubic B-spline with a knot per frame period, fitted by weighted least squares to
        θ(t_b − λ) − θ(t_a − λ) = φ for every band observation inside [ta, tb], with a small penalty
        on the coefficients' second differences (`BAND_SMOOTHING`, the gauge and any knot without
        data). Returns (derivative, its domain) or (None, None) with fewer observations than knots."""
        import scipy.sparse as sp
        from scipy.interpolate import BSpline
        from scipy.sparse.linalg import spsolve

        b = self.bands
        sel = (b["t0"] >= ta - 1e-9) & (b["t1"] <= tb + 1e-9)
        if not sel.any():
            return None, None
        a0, a1 = b["t0"][sel] - b["lag"][sel], b["t1"][sel] - b["lag"][sel]
        phi, w = b["phi"][sel], 1.0 / b["sigma"][sel] ** 2
        lo, hi = float(a0.min()), float(a1.max())
        period = float(np.median(np.diff(self.frame_t)))
        n_inner = max(2, int(math.ceil((hi - lo) / period)) + 1)
        inner = np.linspace(lo, hi, n_inner)
        knots = np.r_[[lo] * 3, inner, [hi] * 3]
        n_coef = len(knots) - 4
        if sel.sum() < n_coef:
            return None, None
        A = BSpline.design_matrix(np.clip(a1, lo, hi), knots, 3) - BSpline.design_matrix(np.clip(a0, lo, hi),
                                                                                          knots, 3)
        A = sp.csr_matrix(A)
        W = sp.diags(w)
        D = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n_coef - 2, n_coef))
        mu = BAND_SMOOTHING * float(np.median(w))
        N = (A.T @ W @ A + mu * (D.T @ D) + 1e-9 * mu * sp.eye(n_coef)).tocsc()
        c = np.column_stack([spsolve(N, A.T @ (w * phi[:, i])) for i in range(3)])
        return BSpline(knots, c, 3).derivative(), (lo, hi)

    def to_dict(self) -> dict:
        known = self.known
        rate = np.linalg.norm(self.rate_at_frames()[known], axis=1) if known.any() else np.zeros(1)
        return {"intervals": len(known), "known": int(known.sum()), "lag_s": self.lag_s,
                "flagged_frames": self.flagged(),
                "overlay_fraction": float(self.overlay.mean()) if self.overlay is not None else 0.0,
                "rate_rms_deg_s": math.degrees(float(np.sqrt(np.mean(rate**2)))),
                "sigma_median_rad": float(np.nanmedian(self.sigma_rad)) if known.any() else None}


# ---------------------------------------------------------------------------------------------- parts
def _work_frames(frames, width: int) -> tuple[list[np.ndarray], float]:
    """Every frame normalised (`normalise_frame`) and shrunk to `width` (INTER_AREA), float32."""
    import cv2

    h0, w0 = np.shape(frames[0])
    scale = min(1.0, width / w0)
    size = (max(16, int(round(w0 * scale))), max(16, int(round(h0 * scale))))
    out = []
    for k in range(len(frames)):
        z = normalise_frame(frames[k])
        out.append(cv2.resize(z, size, interpolation=cv2.INTER_AREA) if scale < 1 else z)
    return out, size[0] / w0


def duplicates(work: list[np.ndarray]) -> np.ndarray:
    """[N] bool: frame k repeats frame k−1 (module docstring, 2)."""
    d = np.array([float(np.median(np.abs(b - a))) for a, b in zip(work[:-1], work[1:], strict=True)])
    typical = float(np.median(d)) if len(d) else 0.0
    dup = (d < DUPLICATE_RATIO * typical) & (d < DUPLICATE_ABS) if typical > 0 else np.zeros(len(d), bool)
    return np.r_[False, dup]


def static_overlay(work: list[np.ndarray], still: np.ndarray | None = None) -> np.ndarray | None:
    """The working-resolution mask of a static overlay, or None (module docstring, 1): `overlay_mask`
    of the mean gradient and mean change over consecutive frames (duplicates, `still`, left out)."""
    n = len(work)
    if n < 3:
        return None
    still = np.zeros(n, bool) if still is None else still
    G = np.zeros_like(work[0])
    D = np.zeros_like(work[0])
    m = 0
    for k in range(1, n):
        if still[k]:
            continue
        G += gradient_magnitude(work[k])
        D += np.abs(work[k] - work[k - 1])
        m += 1
    if m < 2:
        return None
    return overlay_mask(G / m, D / m)


def gradient_magnitude(z: np.ndarray) -> np.ndarray:
    """|∇z| per pixel (Sobel, per pixel of displacement)."""
    import cv2

    gx = cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=3) / 8
    return np.hypot(gx, gy)


def scene_motion(G: np.ndarray, D: np.ndarray) -> float | None:
    """The median D/G of the textured pixels (G above the frame's 75th percentile): about the scene's
    motion in pixels per frame; None on a flat picture (fewer than 16 textured pixels)."""
    textured = G > np.percentile(G, 75)
    if textured.sum() < 16:          # a flat picture: nothing printed on it can be told apart
        return None
    return float(np.median(D[textured] / np.maximum(G[textured], 1e-6)))


def overlay_mask(G: np.ndarray, D: np.ndarray) -> np.ndarray | None:
    """The static overlay from a pixel's mean gradient G = mean |∇z| and mean frame-to-frame change
    D = mean |z_{k+1} − z_k|, or None. A textured pixel (G above the frame's 75th percentile) moving
    with the scene has D/G of the order of its motion in pixels; a printed one has D/G near zero. The
    overlay is the textured pixels with D/G < `OVERLAY_STILL_SHARE` × the median textured pixel's,
    when that one moves (D/G ≥ `OVERLAY_MOVING_RATIO`), dilated; none when it would cover more than
    `OVERLAY_MAX_FRACTION` of the frame (a still camera)."""
    import cv2

    moving = scene_motion(G, D)
    if moving is None or not moving >= OVERLAY_MOVING_RATIO:
        return None
    textured = G > np.percentile(G, 75)
    ratio = D / np.maximum(G, 1e-6)
    mask = (textured & (ratio < OVERLAY_STILL_SHARE * moving)).astype(np.uint8)
    # lone pixels are noise; an overlay is a cluster of printed strokes
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    if mask.sum() < 4:
        return None
    mask = cv2.dilate(mask, np.ones((2 * OVERLAY_DILATE_PX + 1,) * 2, np.uint8))
    if mask.mean() > OVERLAY_MAX_FRACTION:
        return None
    return mask.astype(bool)


def full_resolution(overlay: np.ndarray, width: int, height: int) -> np.ndarray:
    """A working-resolution overlay mask at the frames' `width` × `height` (uint8, 1 = overlay),
    grown by one px (the nearest-neighbour resize's staircase)."""
    import cv2

    m = cv2.resize(overlay.astype(np.uint8), (int(width), int(height)), interpolation=cv2.INTER_NEAREST)
    return cv2.dilate(m, np.ones((3, 3), np.uint8))


class _Inpainted:
    """Frames with the overlay inpainted from their surroundings, one at a time (a lazy sequence)."""

    def __init__(self, frames, mask_full: np.ndarray | None, index: np.ndarray):
        self.frames, self.mask, self.index = frames, mask_full, index

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> np.ndarray:
        import cv2

        f = np.asarray(self.frames[int(self.index[i])])
        if self.mask is None:
            return f
        if f.dtype not in (np.uint8, np.uint16):
            f = f.astype(np.float32)
        return cv2.inpaint(f, self.mask, 3, cv2.INPAINT_TELEA)


def registered_ncc(a: np.ndarray, b: np.ndarray, rotvec: np.ndarray, work: Intrinsics,
                   mask: np.ndarray | None) -> float:
    """Normalised correlation of working frame `a` with `b` warped into it by the rotation (v_a = Q v_b:
    H = K Q K⁻¹), over the pixels both see (overlay left out)."""
    import cv2

    from thermod.physics.geometry import so3_exp

    H = work.K @ so3_exp(rotvec) @ work.K_inv
    h, w = a.shape
    # pixel p of a sees the ray of H⁻¹ p in b
    warped = cv2.warpPerspective(b, np.linalg.inv(H), (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderValue=np.nan)
    ok = np.isfinite(warped)
    m = max(2, w // 40)
    ok[:m], ok[-m:], ok[:, :m], ok[:, -m:] = False, False, False, False
    if mask is not None:
        ok &= ~mask
    if ok.sum() < 0.1 * a.size:
        return math.nan
    x, y = a[ok] - a[ok].mean(), warped[ok] - warped[ok].mean()
    den = float(np.sqrt(np.sum(x * x) * np.sum(y * y)))
    return float(np.sum(x * y) / den) if den > 0 else math.nan


def _outliers(rotvec: np.ndarray, t: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """[K] bool: intervals whose mean rate is far from what their neighbours predict.

    Each measured interval's rate is predicted by a quadratic in time through the measured rates of the
    two intervals either side (at least three of them); it is an outlier when it misses by more than
    `OUTLIER_K` × the median miss of the video and by more than `OUTLIER_MIN_RAD_S` (a body's rate is
    smooth on the scale of a frame; a fit locked onto a wrong match is not)."""
    mid = 0.5 * (t[1:] + t[:-1])
    rate = rotvec / np.diff(t)[:, None]
    n = len(rate)
    miss = np.full(n, np.nan)
    for i in np.flatnonzero(ok):
        nb = [j for j in (i - 2, i - 1, i + 1, i + 2) if 0 <= j < n and ok[j]]
        if len(nb) < 3:
            continue
        x = mid[nb] - mid[i]
        V = np.vander(x, 3)
        coef, *_ = np.linalg.lstsq(V, rate[nb], rcond=None)
        miss[i] = float(np.linalg.norm(rate[i] - coef[-1]))
    if not np.isfinite(miss).any():
        return np.zeros(n, bool)
    limit = max(OUTLIER_K * float(np.nanmedian(miss)), OUTLIER_MIN_RAD_S)
    return np.nan_to_num(miss, nan=0.0) > limit


# ----------------------------------------------------------------------------------------------- main
def _smoothed_rate(knots: np.ndarray, theta: np.ndarray):
    """The rate of measured angles θ [n, 3] at the knots: per axis, the derivative of a cubic
    smoothing spline whose smoothing generalised cross-validation chooses
    (`scipy.interpolate.make_smoothing_spline`), over an abscissa in frame periods. τ's fit regresses
    the comet tails on the rate, and noise in a regressor biases its fit: through the interpolating
    spline's rate τ came out 10–25 % short on the real flight's clips, 8–11 % through this one
    (benchmarks/results/video_tau.md)."""
    from scipy.interpolate import make_smoothing_spline

    # in frame periods: with the abscissa in seconds the cross-validation's search flattened a 2 Hz sway
    t0, period = float(knots[0]), float(np.median(np.diff(knots)))
    x = (knots - t0) / period
    axes = [make_smoothing_spline(x, theta[:, a]).derivative() for a in range(theta.shape[1])]
    return lambda t: np.stack([d((np.asarray(t) - t0) / period) for d in axes], axis=-1) / period


def estimate_track(frames, frame_t, intrinsics: Intrinsics, *, tau_s: float, readout_s: float = 0.0,
                   work_width: int = WORK_WIDTH, name: str = "video", progress=None) -> RotationTrack:
    """The rotation track of a video (module docstring). `frames` [N, H, W] grey or a sequence of
    [H, W] frames (AGC allowed); `frame_t` [N] s (a frame's time: its last row read); `tau_s`,
    `readout_s` the camera's. Raises `TrackError` naming `name` when the video is too short, its
    frames too far apart (`MAX_PERIOD_S`) or it has too little texture to track."""

    n = len(frames)
    t = np.asarray(frame_t, np.float64)
    if n < MIN_FRAMES:
        raise TrackError(f"{name}: {n} frame(s); a rotation track from the pictures needs ≥ {MIN_FRAMES}")
    if t.shape != (n,) or not np.all(np.isfinite(t)) or not np.all(np.diff(t) > 0):
        raise TrackError(f"{name}: frame times must be {n} finite, increasing seconds")
    period = float(np.median(np.diff(t)))
    if period > MAX_PERIOD_S:
        raise TrackError(f"{name}: the frames are {period:.4g} s apart at the median ({1 / period:.3g} fps): "
                         "the camera's rotation during a frame cannot be told from pictures so far apart; "
                         f"expected at least {1 / MAX_PERIOD_S:g} fps (a wrong time base?)")
    shape = np.shape(frames[0])
    if shape != (intrinsics.height, intrinsics.width):
        raise TrackError(f"{name}: {shape[1] if len(shape) > 1 else '?'}×{shape[0]} px frames but the "
                         f"camera is {intrinsics.width}×{intrinsics.height}")
    work, scale = _work_frames(frames, work_width)
    dup = duplicates(work)
    overlay = static_overlay(work, dup)
    mask_full = None if overlay is None else full_resolution(overlay, intrinsics.width, intrinsics.height)
    kept = np.flatnonzero(~dup)
    try:
        pm = picture_motion(_Inpainted(frames, mask_full, kept), t[kept], intrinsics, work_width=work_width,
                            smooth_px=SMOOTH_PX, progress=progress)
    except MotionError as e:
        raise TrackError(f"{name}: {e}") from None
    noise = pm.noise_rad()
    rv = pm.rotvec.copy()
    # the picture motion's working frames may differ in size from ours by rounding: compare at ours
    wk_ours = intrinsics.scaled(work[0].shape[1] / intrinsics.width) if scale < 1 else intrinsics
    tk = t[kept]
    ncc = np.full(len(kept) - 1, np.nan)
    status_kept = np.full(len(kept) - 1, "ok", dtype=object)
    long = np.diff(t) > GAP_PERIODS * period
    for i in range(len(kept) - 1):
        if long[kept[i]:kept[i + 1]].any():    # the rate inside it unknown: a hole, never a spline's guess
            status_kept[i] = "gap"
            continue
        if not pm.valid[i]:
            status_kept[i] = "untracked"
            continue
        ncc[i] = registered_ncc(work[kept[i]], work[kept[i + 1]], rv[i], wk_ours, overlay)
        if not ncc[i] >= MIN_REGISTERED_NCC:
            status_kept[i] = "cut"
    status_kept[_outliers(rv, tk, status_kept == "ok")] = "untracked"
    retried = np.zeros(len(kept) - 1, bool)
    measured = status_kept == "ok"
    if measured.sum() < max(MIN_FRAMES - 1, MIN_MEASURED_FRACTION * int(np.sum(status_kept != "gap"))):
        raise TrackError(f"{name}: the camera rotation could be measured between only {int(measured.sum())} "
                         f"of {len(measured)} frame pairs (need ≥ {MIN_MEASURED_FRACTION:.0%}): too little "
                         "texture to track, or no frame like the next")
    # back to every frame: a duplicate's interval pair shares the rotation across it by time
    rotvec = np.full((n - 1, 3), np.nan)
    sigma = np.full(n - 1, np.nan)
    status = np.full(n - 1, "ok", dtype=object)
    ncc_all = np.full(n - 1, np.nan)
    for i in range(len(kept) - 1):
        a, b = int(kept[i]), int(kept[i + 1])
        span = t[b] - t[a]
        for k in range(a, b):
            share = (t[k + 1] - t[k]) / span
            if status_kept[i] == "ok":
                rotvec[k] = rv[i] * share
                sigma[k] = noise[i] * share
            status[k] = status_kept[i] if status_kept[i] != "ok" else ("duplicate" if dup[k + 1] else "ok")
            ncc_all[k] = ncc[i]
    # the frames after the last kept one (trailing duplicates): hold nothing, unknown
    for k in range(int(kept[-1]), n - 1):
        status[k] = "duplicate"
    lag = tau_s + 0.5 * readout_s
    bands = _band_observations(pm, rv, noise, t[kept], status_kept == "ok", retried, tau_s,
                               readout_s) if readout_s > 0 else {}
    return RotationTrack(t.copy(), rotvec, sigma, status.astype(str), lag, overlay, scale, ncc_all, bands)


def _band_observations(pm, rv, noise, t_kept: np.ndarray, ok: np.ndarray, retried: np.ndarray, tau_s: float,
                       readout_s: float) -> dict:
    """The band rotations of the intervals measured (`ok`) as observations at their own lags, τ + the
    band's mean lead × readout (the whole frame's, `rv`, at τ + ½ readout where no band has enough
    corners or the interval was `retried` smaller)."""
    t0, t1, lag, phi, sig = [], [], [], [], []
    for i in np.flatnonzero(ok):
        got = False
        for b in range(pm.band_rotvec.shape[1]) if not retried[i] else ():
            if np.all(np.isfinite(pm.band_rotvec[i, b])):
                t0.append(t_kept[i])
                t1.append(t_kept[i + 1])
                lag.append(tau_s + pm.band_lead[i, b] * readout_s)
                phi.append(pm.band_rotvec[i, b])
                sig.append(math.sqrt(np.trace(np.linalg.inv(pm.band_info[i, b])) / 3.0))
                got = True
        if not got:
            t0.append(t_kept[i])
            t1.append(t_kept[i + 1])
            lag.append(tau_s + 0.5 * readout_s)
            phi.append(rv[i])
            sig.append(noise[i])
    if not t0:
        return {}
    return {"t0": np.array(t0), "t1": np.array(t1), "lag": np.array(lag), "phi": np.array(phi),
            "sigma": np.array(sig)}
