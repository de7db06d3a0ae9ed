"""Fast forward model: predict blurry microbolometer frames from a static reference view and raw gyro.

The physics is the simulator's, written for speed instead of fidelity to a high-resolution scene:

* the view at time s is the reference warped by the rotation-only homography (Eq. 16)
  ``H(s) = K Q(s) K⁻¹`` with ``Q(s) = R(t_ref)ᵀ R(s)`` integrated from the calibrated gyro with the
  piecewise-linear rate semantics of `thermod.physics.geometry.integrate_rotations`;
* the detector is the first-order thermal low-pass (Eq. 10/11), run as an exact IIR over sub-pixel
  time steps (Eq. 12: the image moves < `max_step_px` per step), so each frame is the exponential
  average of the views over its past (≥ 5τ of weight, Eq. 18);
* rolling readout: row r of a frame read at t_k is sampled at ``t_k − T_ro·(1 − (r+1)/H)``;
* optical PSF: an optional *extra* Gaussian (Eq. 19) on top of whatever blur the reference has.

The reference is a measured static frame, so it already carries the detector's own optical PSF
(and the same FPN as every frame): the prediction therefore needs no PSF of its own, and
`extra_psf_px` is the blur that motion frames show *beyond* the static ones (0 for a correct model).

Work happens at a reduced resolution (`scale`, intrinsics scaled with `Intrinsics.scaled`), on a
fixed time grid that does not depend on the candidate parameters, so that the warped views can be
cached while only τ, the readout time or the extra PSF change.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from thermod.physics.calibration import GYRO_EFFECT_KEYS, Calibration
from thermod.physics.detector import iir_alpha, row_read_time
from thermod.physics.geometry import integrate_rotations

__all__ = ["ForwardModel", "GridTooLarge", "downsample", "orientations", "predict_frames"]


WARP_COST = 8             # a warped view's pixel against an IIR step's (`ForwardModel.work`)
VIEW_CACHE_ENTRIES = 2    # calibrations whose warped views are kept (one search point and its neighbour)


class GridTooLarge(ValueError):
    """The fixed time grid would need more memory for its warped views than allowed: `views_mb` it
    would take; `tau_limited` when the thermal step (τ), not the image speed, sets most of its steps."""

    def __init__(self, message: str, views_mb: float = math.inf, tau_limited: bool = False):
        super().__init__(message)
        self.views_mb, self.tau_limited = views_mb, tau_limited


def downsample(frames: np.ndarray, scale: float, smooth_px: float = 0.0) -> np.ndarray:
    """Area-average frames [.., H, W] to `scale` × their size (float32), matching `Intrinsics.scaled`.

    `smooth_px` > 0 adds a Gaussian low-pass (σ in output pixels) that removes the aliased
    frequencies, so that warping the small image and shrinking a warped big one agree.
    """
    frames = np.asarray(frames, dtype=np.float32)
    one = frames.ndim == 2
    stack = frames[None] if one else frames
    h, w = stack.shape[-2:]
    size = (int(round(w * scale)), int(round(h * scale)))
    out = []
    for f in stack:
        g = f.copy() if scale == 1.0 else cv2.resize(f, size, interpolation=cv2.INTER_AREA)
        if smooth_px > 0:
            g = cv2.GaussianBlur(g, (0, 0), smooth_px, borderType=cv2.BORDER_REPLICATE)
        out.append(g)
    out = np.stack(out)
    return out[0] if one else out


def orientations(t_query: np.ndarray, t_cam: np.ndarray, omega_cam: np.ndarray, t_ref: float) -> np.ndarray:
    """Q(t) = R(t_ref)ᵀ R(t) at arbitrary times, same semantics as `geometry.integrate_rotations`.

    The rate is piecewise linear between gyro samples and held constant outside them; query times
    and t_ref are merged into the sample times, and `integrate_rotations` integrates the lot.
    """
    t_query = np.asarray(t_query, dtype=np.float64)
    lo = min(t_query.min(), t_ref)
    hi = max(t_query.max(), t_ref)
    keep = (t_cam > lo) & (t_cam < hi)
    tt, inv = np.unique(np.concatenate([t_query, [t_ref], t_cam[keep]]), return_inverse=True)
    if len(t_cam) == 1:
        ww = np.repeat(omega_cam[:1], len(tt), axis=0)
    else:
        ww = np.stack([np.interp(tt, t_cam, omega_cam[:, a]) for a in range(3)], axis=1)
    return integrate_rotations(tt, ww, t_ref)[inv[: len(t_query)]]


def _weight_centroid(h: np.ndarray, tau: float) -> np.ndarray:
    """Mean age of the exponential weight e^{−a/τ} over a step's a ∈ [0, h]: τ − h/(e^{h/τ} − 1)
    (h/2 − h²/(12τ) for short steps, 0 without thermal lag)."""
    h = np.asarray(h, np.float64)
    if tau <= 0:
        return np.zeros_like(h)
    x = h / tau
    small = x < 1e-3
    xs = np.where(small, 1.0, x)
    return np.where(small, h / 2 - h * x / 12, tau - h / np.expm1(xs))


# ------------------------------------------------------------------ compiled kernels (one core, no threads)
@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _taps(f, cubic, w):
    """Interpolation weights of the 4 taps at offsets −1..2 for fractional position f (OpenCV's cubic,
    Keys a = −0.75, or linear)."""
    if cubic:
        a = -0.75
        x = f + 1.0
        w[0] = ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
        w[1] = ((a + 2.0) * f - (a + 3.0)) * f * f + 1.0
        g = 1.0 - f
        w[2] = ((a + 2.0) * g - (a + 3.0)) * g * g + 1.0
        w[3] = 1.0 - w[0] - w[1] - w[2]
    else:
        w[0] = 0.0
        w[1] = 1.0 - f
        w[2] = f
        w[3] = 0.0


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _cubic_taps(f):
    """OpenCV's cubic weights (Keys a = −0.75) of the taps at offsets −1..2 for fractional position f."""
    a = -0.75
    x = f + 1.0
    w0 = ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
    w1 = ((a + 2.0) * f - (a + 3.0)) * f * f + 1.0
    g = 1.0 - f
    w2 = ((a + 2.0) * g - (a + 3.0)) * g * g + 1.0
    return w0, w1, w2, 1.0 - w0 - w1 - w2


@njit(cache=True, nogil=True, fastmath=True)
def _interior(sup):
    """1 at (iv, iu) where all 16 taps rows iv−1..iv+2, columns iu−1..iu+2 lie in the canvas and its
    support: there a view pixel is one plain 4×4 sum and its support weight is exactly 1."""
    ch, cw = sup.shape
    out = np.zeros((ch, cw), np.uint8)
    for iv in range(1, ch - 2):
        for iu in range(1, cw - 2):
            ok = 1
            for a in range(-1, 3):
                for b in range(-1, 3):
                    if sup[iv + a, iu + b] != 1.0:
                        ok = 0
            out[iv, iu] = ok
    return out


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _row_positions(H, y, ox, oy, us, vs, taps):
    """Where row y's pixels land in the canvas, (us, vs) = H (x, y, 1) + o for every x (−1e30 where the
    homography sends them behind the camera), and their cubic taps: taps[0..3] along u, taps[4..7]
    along v. One branch-free pass over the row, which vectorises; the gathers and scatters that
    follow then do no division and no tap arithmetic (1.6× faster than computing them per pixel)."""
    w = us.shape[0]
    X = H[0, 1] * y + H[0, 2]
    Y = H[1, 1] * y + H[1, 2]
    Z = H[2, 1] * y + H[2, 2]
    for x in range(w):
        Zx = Z + H[2, 0] * x
        ok = Zx > 1e-9
        Zs = Zx if ok else 1.0
        u = (X + H[0, 0] * x) / Zs + ox
        v = (Y + H[1, 0] * x) / Zs + oy
        u = u if ok else -1e30
        v = v if ok else -1e30
        us[x] = u
        vs[x] = v
        fu = u - math.floor(u)
        fv = v - math.floor(v)
        taps[0, x], taps[1, x], taps[2, x], taps[3, x] = _cubic_taps(fu)
        taps[4, x], taps[5, x], taps[6, x], taps[7, x] = _cubic_taps(fv)


@njit(cache=True, nogil=True, fastmath=True)
def _warp_views(S, sup, inner, Hs, ox, oy, cubic, out_v, out_m):
    """out_v[j](x) = S(H_j x + o), out_m[j](x) = support(H_j x + o): the canvas sampled with zero outside
    it (what OpenCV's warpPerspective with WARP_INVERSE_MAP and a constant 0 border does).

    `inner` (`_interior` of the support) marks the positions whose taps are all known: one 4×4 sum
    there (most pixels), the bounds- and support-checked sum only near the canvas edge.
    """
    n, h, w = out_v.shape
    ch, cw = S.shape
    wx = np.empty(4)
    wy = np.empty(4)
    us = np.empty(w)
    vs = np.empty(w)
    taps = np.empty((8, w))
    for j in range(n):
        H = Hs[j]
        for y in range(h):
            ov = out_v[j, y]
            om = out_m[j, y]
            _row_positions(H, y, ox, oy, us, vs, taps)
            for x in range(w):
                u = us[x]
                v = vs[x]
                if u < -2.0 or v < -2.0 or u > cw + 1.0 or v > ch + 1.0:
                    ov[x] = 0.0
                    om[x] = 0.0
                    continue
                iu = int(math.floor(u))
                iv = int(math.floor(v))
                if cubic and iu >= 1 and iv >= 1 and iu + 2 < cw and iv + 2 < ch and inner[iv, iu]:
                    x0, x1, x2, x3 = taps[0, x], taps[1, x], taps[2, x], taps[3, x]
                    y0, y1, y2, y3 = taps[4, x], taps[5, x], taps[6, x], taps[7, x]
                    r0 = S[iv - 1]
                    r1 = S[iv]
                    r2 = S[iv + 1]
                    r3 = S[iv + 2]
                    ov[x] = (y0 * (x0 * r0[iu - 1] + x1 * r0[iu] + x2 * r0[iu + 1] + x3 * r0[iu + 2])
                             + y1 * (x0 * r1[iu - 1] + x1 * r1[iu] + x2 * r1[iu + 1] + x3 * r1[iu + 2])
                             + y2 * (x0 * r2[iu - 1] + x1 * r2[iu] + x2 * r2[iu + 1] + x3 * r2[iu + 2])
                             + y3 * (x0 * r3[iu - 1] + x1 * r3[iu] + x2 * r3[iu + 1] + x3 * r3[iu + 2]))
                    om[x] = 1.0
                    continue
                _taps(u - iu, cubic, wx)
                _taps(v - iv, cubic, wy)
                acc = 0.0
                accm = 0.0
                for a in range(4):
                    yy = iv - 1 + a
                    if yy < 0 or yy >= ch or wy[a] == 0.0:
                        continue
                    ra = 0.0
                    rm = 0.0
                    for b in range(4):
                        xx = iu - 1 + b
                        if xx < 0 or xx >= cw:
                            continue
                        ra += wx[b] * S[yy, xx]
                        rm += wx[b] * sup[yy, xx]
                    acc += wy[a] * ra
                    accm += wy[a] * rm
                ov[x] = acc
                om[x] = accm


@njit(cache=True, nogil=True, fastmath=True)
def _iir_rows(V, M, alpha, jj, share, lam, out_v, out_m):
    """Eq. 10/11 over the grid, row by row: B_0 = V_0, B_j = B_{j−1} + α_j (V_j − B_{j−1}).

    Row y of frame k, read in step j = jj[k, y] (after t_{j−1}, at or before t_j), is
    B_{j−1} + φ (V' − B_{j−1}) with φ = share[k, y] = 1 − e^{−s/τ} the weight of the s it spent in the
    step, and V' = λ V_j + (1 − λ) V_{j−1} (λ = lam[k, y]) the view at the centroid of that weight
    (φ = λ = 1 for a row read at a grid node: B_j). j = 0: B_0 (φ = 0). Frames in time order.
    """
    n1, h, w = V.shape
    nf = jj.shape[0]
    b = np.empty(w, np.float32)
    bm = np.empty(w, np.float32)
    pb = np.empty(w, np.float32)
    pm = np.empty(w, np.float32)
    for y in range(h):
        for x in range(w):
            b[x] = V[0, y, x]
            bm[x] = M[0, y, x]
            pb[x] = b[x]
            pm[x] = bm[x]
        j = 0
        for k in range(nf):
            t = jj[k, y]
            while j < t:
                j += 1
                a = alpha[j]
                vj = V[j, y]
                mj = M[j, y]
                for x in range(w):
                    pb[x] = b[x]
                    pm[x] = bm[x]
                    b[x] += a * (vj[x] - b[x])
                    bm[x] += a * (mj[x] - bm[x])
            f = share[k, y]
            lj = lam[k, y]
            li = 1.0 - lj
            v1 = V[t, y]
            m1 = M[t, y]
            v0 = V[max(t - 1, 0), y]
            m0 = M[max(t - 1, 0), y]
            for x in range(w):
                out_v[k, y, x] = pb[x] + f * (lj * v1[x] + li * v0[x] - pb[x])
                out_m[k, y, x] = pm[x] + f * (lj * m1[x] + li * m0[x] - pm[x])


@njit(cache=True, nogil=True, fastmath=True)
def _adjoint_rows(C, alpha, jj, share, lam, Hs, ox, oy, cubic, grad):
    """Adjoint of `_iir_rows` ∘ `_warp_views` with respect to the canvas S: grad += Aᵀ C.

    C: cotangent of the predicted frames [n_frames, h, w]. The IIR is run backwards in time: g, the
    cotangent of B_j, collects (1 − φ) C of the rows read in step j + 1 and (1 − α_{j+1}) of the
    later state's; view j gets α_j g (all of g for the initial view B_0 = V_0) plus its direct share
    φλ C (rows read in step j) and φ(1 − λ) C (rows read in step j + 1), scattered through the
    interpolation taps at H_j x + o.
    """
    nf, h, w = C.shape
    ch, cw = grad.shape
    g = np.zeros(w)
    dv = np.zeros(w)
    wx = np.empty(4)
    wy = np.empty(4)
    us = np.empty(w)
    vs = np.empty(w)
    taps = np.empty((8, w))
    for y in range(h):
        for x in range(w):
            g[x] = 0.0
        jmax = 0
        for kk in range(nf):
            jmax = max(jmax, jj[kk, y])
        for j in range(jmax, -1, -1):
            for x in range(w):
                dv[x] = 0.0
            for kk in range(nf):
                t = jj[kk, y]
                if t == j:
                    c1 = share[kk, y] * lam[kk, y]
                    for x in range(w):
                        dv[x] += c1 * C[kk, y, x]
                elif t == j + 1:
                    f = share[kk, y]
                    c0 = f * (1.0 - lam[kk, y])
                    for x in range(w):
                        g[x] += (1.0 - f) * C[kk, y, x]
                        dv[x] += c0 * C[kk, y, x]
            a_j = alpha[j] if j > 0 else 1.0
            _row_positions(Hs[j], y, ox, oy, us, vs, taps)
            for x in range(w):
                gv = a_j * g[x] + dv[x]
                if gv == 0.0:
                    continue
                u = us[x]
                v = vs[x]
                if u < -2.0 or v < -2.0 or u > cw + 1.0 or v > ch + 1.0:
                    continue
                iu = int(math.floor(u))
                iv = int(math.floor(v))
                if cubic and iu >= 1 and iv >= 1 and iu + 2 < cw and iv + 2 < ch:
                    # every tap inside the canvas (most pixels): the 16 products unrolled, as in
                    # `_warp_views`' fast path
                    x0, x1, x2, x3 = taps[0, x], taps[1, x], taps[2, x], taps[3, x]
                    for a in range(4):
                        r = grad[iv - 1 + a]
                        gy = gv * taps[4 + a, x]
                        r[iu - 1] += gy * x0
                        r[iu] += gy * x1
                        r[iu + 1] += gy * x2
                        r[iu + 2] += gy * x3
                    continue
                _taps(u - iu, cubic, wx)
                _taps(v - iv, cubic, wy)
                for a in range(4):
                    yy = iv - 1 + a
                    if yy < 0 or yy >= ch or wy[a] == 0.0:
                        continue
                    for bb in range(4):
                        xx = iu - 1 + bb
                        if xx < 0 or xx >= cw:
                            continue
                        grad[yy, xx] += gv * wy[a] * wx[bb]
            if j > 0:
                for x in range(w):
                    g[x] *= 1.0 - alpha[j]


class ForwardModel:
    """Predicts one recording's frames for any calibration, caching what does not change.

    Parameters
    ----------
    reference : float32 [H, W]
        Sharp view at full resolution, in counts, with FPN already removed if known (a static mean, or
        any frame to start from: `set_reference` replaces it by a canvas at the working resolution).
    frame_t : float64 [n]
        Camera times of the frames to predict (when their last row was read), all > `t_start`.
    gyro_t, gyro_rate : raw gyro samples (gyro clock, gyro frame, rad/s).
    calib : Calibration
        Nominal model; it fixes the image size, intrinsics and the step size of the time grid.
    t_ref : float
        The camera time of the reference view: Q(t_ref) = I, so the reference is the sharp view the
        camera had then (a static pose, or any moment of the motion).
    t_start : float or None
        Start of the time grid (default `t_ref`): the detector is taken as settled on the view at
        t_start (the reference itself when t_start = t_ref; frames read ≥ 5τ later do not depend on it).
    scale : float
        Working resolution relative to the recording (e.g. 0.5 or 0.25).
    fpn : float32 [H, W] or None
        Fixed-pattern noise, added back after the motion (it stays put on the sensor).
    max_step_px : float
        Largest image motion per time step (Eq. 12), at the working resolution.
    max_rate_factor : float
        Head-room on the gyro rate when choosing the step, so candidate scales stay sub-pixel.
    max_step_tau : float
        Largest time step as a fraction of the nominal τ (or τ_min/4 when `tau_min_s` is given).
    time_margin_s : float
        The step near a time t follows the fastest motion within ± this (candidate time offsets move it).
    cache_mb : float
        Memory allowed for cached warped views: the views of the last `VIEW_CACHE_ENTRIES` calibrations
        that fit in it (a search alternates between a point and its neighbour on the same scene).
    max_views_mb : float
        Memory the warped views of one prediction may take at all; GridTooLarge beyond it (checked
        before anything is allocated: the step count follows from the gyro rate, fx and τ).
    prescaled : bool
        `reference` (and `fpn`) are at the working resolution already.
    interpolation : "cubic" (default: least resampling blur; OpenCV's Keys kernel) or "linear".

    The views are sampled by a compiled kernel (one core, no threads): the reference canvas at
    ``H(s) x + origin`` with zero outside it, and its support (1 where the canvas is known) the same
    way, so a pixel's IIR-weighted support says how much of its past came from known scene.
    """

    def __init__(self, reference, frame_t, gyro_t, gyro_rate, calib: Calibration, *, t_ref: float,
                 scale: float = 1.0, fpn=None, max_step_px: float = 0.5, max_rate_factor: float = 1.3,
                 tau_min_s: float | None = None, cache_mb: float = 400.0, interpolation: str = "cubic",
                 max_views_mb: float = 4096.0, t_start: float | None = None, max_step_tau: float = 1 / 3,
                 time_margin_s: float = 0.03, prescaled: bool = False):
        self.calib0 = calib
        self.scale = float(scale)
        self.intr = calib.intrinsics.scaled(self.scale)
        self.h, self.w = self.intr.height, self.intr.width
        self.frame_t = np.asarray(frame_t, dtype=np.float64)
        self.gyro_t = np.asarray(gyro_t, dtype=np.float64)
        self.gyro_rate = np.asarray(gyro_rate, dtype=np.float64)
        self.t_ref = float(t_ref)
        self.t_start = self.t_ref if t_start is None else float(t_start)
        if len(self.frame_t) and self.frame_t.min() <= self.t_start:
            raise ValueError("every frame to predict must be read after the grid start")
        if len(self.frame_t) > 1 and np.any(np.diff(self.frame_t) <= 0):
            raise ValueError("frame times must increase")
        # Fixed time grid from t_start (detector settled there) to the last frame, with a node at every
        # frame's read time (rows read there need no interpolation) and sub-steps short enough for the
        # image to move ≤ max_step_px (Eq. 12, local speed) and for the thermal response (≤ τ_min/4).
        tau_min = tau_min_s if tau_min_s is not None else calib.tau_s * 4.0 * max_step_tau
        h_tau = max(tau_min, 1e-4) / 4.0
        nodes = np.unique(np.r_[self.t_start, self.frame_t])
        if len(nodes) == 1:
            nodes = np.r_[self.t_start, self.t_start + h_tau]
        span = np.diff(nodes)
        speed = self._interval_speeds(calib, nodes, time_margin_s) * max_rate_factor
        with np.errstate(divide="ignore"):
            h_move = np.where(speed > 0, max_step_px / np.where(speed > 0, speed, 1.0), np.inf)
        n_sub = np.maximum(1.0, np.ceil(span / np.minimum(h_tau, h_move) - 1e-9))
        n_float = float(np.sum(n_sub))
        views_mb = (n_float + 1) * self.h * self.w * 2 * 4 / 1e6
        if not views_mb <= max_views_mb:
            tau_steps = float(np.sum(np.maximum(1.0, np.ceil(span / h_tau - 1e-9))))
            raise GridTooLarge(f"the forward model needs {n_float:.3g} time steps ({views_mb / 1e3:.3g} GB "
                               f"of warped views, limit {max_views_mb / 1e3:.3g} GB) for "
                               f"{nodes[-1] - self.t_start:.3g} s of motion at up to "
                               f"{float(speed.max()):.3g} px/s (working fx {self.intr.fx:.4g}, "
                               f"τ {calib.tau_s:.3g} s)", views_mb, tau_steps >= 0.5 * n_float)
        n_sub = n_sub.astype(np.int64)
        first = np.repeat(np.cumsum(n_sub) - n_sub, n_sub)
        k = np.arange(int(n_sub.sum())) - first
        self.t_grid = np.r_[np.repeat(nodes[:-1], n_sub) + k * np.repeat(span / n_sub, n_sub), nodes[-1]]
        self.h_steps = np.diff(self.t_grid)
        self.dt = float(self.h_steps.max())
        # The view of a step is taken at the centroid of its exponential weight under the nominal τ
        # (τ − h/(e^{h/τ} − 1) before its end, h/2 for τ → ∞): first-order exact for a view that moves
        # steadily over the step; the IIR then weighs it exactly (Eq. 11).
        self.t_views = np.r_[self.t_grid[0], self.t_grid[1:] - _weight_centroid(self.h_steps, calib.tau_s)]
        if interpolation not in ("linear", "cubic"):
            raise ValueError(f"interpolation must be 'linear' or 'cubic', got {interpolation!r}")
        self._cubic = interpolation == "cubic"
        self._views: dict = {}          # gyro key → (V, M) for the current reference, oldest first
        # Pixel-steps computed so far, weighted by their cost (an IIR pass over [n_steps + 1, h, w] 1, a
        # warp of the views `WARP_COST`: two arrays through 16 cubic taps; the adjoint both):
        # the run-time measure a caller bounds its searches by.
        self.work = 0
        self._cache_slots = min(VIEW_CACHE_ENTRIES, int(cache_mb // max(views_mb, 1e-9)))
        self.origin = (0.0, 0.0)
        self.set_reference(reference, fpn, prescaled=prescaled)

    def set_reference(self, reference, fpn=None, *, prescaled: bool = False, origin=(0.0, 0.0),
                      support=None, subtract_fpn: bool = True) -> None:
        """Replace the reference (and FPN) keeping the time grid; drops the cached views.

        `reference` may be a canvas larger than the frame (prescaled, working resolution): `origin` is
        the canvas position of the reference view's pixel (0, 0) and `support` (float32, canvas shape)
        is 1 where the canvas is known, 0 elsewhere (default: everywhere). `subtract_fpn`: the
        reference carries the FPN (a static mean) and it is removed before warping.
        """
        ref = np.asarray(reference, np.float32) if prescaled else downsample(reference, self.scale)
        if fpn is not None:
            fpn = np.asarray(fpn, np.float32) if prescaled else downsample(fpn, self.scale)
        self.fpn = fpn
        ox, oy = float(origin[0]), float(origin[1])
        if subtract_fpn and fpn is not None:
            ref = ref.copy()
            iy, ix = int(round(oy)), int(round(ox))
            ref[iy:iy + self.h, ix:ix + self.w] -= fpn
        self.reference = np.ascontiguousarray(ref, np.float32)
        self.support = (np.ones_like(self.reference) if support is None
                        else np.ascontiguousarray(support, np.float32))
        if self.support.shape != self.reference.shape:
            raise ValueError("support must have the reference canvas's shape")
        self.origin = (ox, oy)
        self._inner = _interior(self.support)
        iy, ix = int(round(oy)), int(round(ox))
        view = np.zeros((self.h, self.w), np.float32)
        crop = self.reference[iy:iy + self.h, ix:ix + self.w]
        view[:crop.shape[0], :crop.shape[1]] = crop
        self.reference_view = view          # the reference's own view (fallback where nothing is valid)
        self._views = {}

    # ------------------------------------------------------------------ geometry
    def _interval_speeds(self, calib: Calibration, nodes: np.ndarray, margin_s: float) -> np.ndarray:
        """Fastest image motion (working px/s at the frame corners) of the gyro samples within ± margin_s
        of each interval between consecutive nodes (and the samples either side: the rate is
        interpolated between them); 0 without gyro samples."""
        t, w = calib.gyro_to_camera(self.gyro_t, self.gyro_rate)
        if len(w) == 0:
            return np.zeros(len(nodes) - 1)
        f = max(self.intr.fx, self.intr.fy)
        r = math.hypot(self.w, self.h) / 2.0   # roll moves the corners by |ω_z|·r
        speed = f * np.hypot(w[:, 0], w[:, 1]) + r * np.abs(w[:, 2])
        i0 = np.clip(np.searchsorted(t, nodes[:-1] - margin_s, side="right") - 1, 0, len(t) - 1)
        i1 = np.clip(np.searchsorted(t, nodes[1:] + margin_s, side="left") + 1, 1, len(t))
        # a range maximum per interval; intervals are few (one per frame)
        return np.array([speed[a:max(b, a + 1)].max() for a, b in zip(i0.tolist(), i1.tolist(), strict=True)])

    def homographies(self, calib: Calibration, times: np.ndarray) -> np.ndarray:
        """H(s) = K Q(s) K⁻¹ (Eq. 16) at the working resolution for camera times `times`."""
        t_cam, w_cam = calib.gyro_to_camera(self.gyro_t, self.gyro_rate)
        Q = orientations(times, t_cam, w_cam, self.t_ref)
        K = self.intr.K
        return K[None] @ Q @ np.linalg.inv(K)[None]

    def _gyro_key(self, calib: Calibration):
        return (calib.time_offset_s, tuple(calib.bias_rad_s), tuple(np.ravel(calib.gyro_to_camera_matrix)),
                tuple(getattr(calib, k) for k in GYRO_EFFECT_KEYS), calib.gyro_clip_run_gains)

    def views(self, calib: Calibration):
        """Reference and support sampled at the view times (grid start, then every step's mid-point):
        two float32 [n_steps + 1, h, w] arrays."""
        key = self._gyro_key(calib)
        if (hit := self._views.pop(key, None)) is not None:
            self._views[key] = hit            # now the newest
            return hit
        Hs = np.ascontiguousarray(self.homographies(calib, self.t_views))
        self.work += WARP_COST * len(Hs) * self.h * self.w
        V = np.empty((len(Hs), self.h, self.w), np.float32)
        M = np.empty_like(V)
        _warp_views(self.reference, self.support, self._inner, Hs, self.origin[0], self.origin[1],
                    self._cubic, V, M)
        if self._cache_slots:
            while len(self._views) >= self._cache_slots:
                del self._views[next(iter(self._views))]
            self._views[key] = (V, M)
        return V, M

    def row_times(self, calib: Calibration) -> np.ndarray:
        """Read time of every working row of every frame: [n_frames, h]."""
        y_full = (np.arange(self.h) + 0.5) / self.scale - 0.5
        return row_read_time(self.frame_t[:, None], y_full[None, :], calib.readout_s, calib.height)

    def _row_steps(self, calib: Calibration):
        """Where each frame row is read on the grid (see `_iir_rows`): (j, φ, λ) per row, [n_frames, h]:
        read in step j (in (t_{j−1}, t_j]) after s of it, φ = 1 − e^{−s/τ}, λ placing the view at the
        centroid of that weight between the views of steps j − 1 and j (j = 0, φ = 0 at or before
        t_start)."""
        rt = np.clip(self.row_times(calib), self.t_grid[0], self.t_grid[-1])
        jj = np.clip(np.searchsorted(self.t_grid, rt, side="left"), 0, len(self.t_grid) - 1)
        jm = np.maximum(jj - 1, 0)
        s = np.clip(rt - self.t_grid[jm], 0.0, self.h_steps[jm])
        share = -np.expm1(-s / calib.tau_s) if calib.tau_s > 0 else (s > 0).astype(np.float64)
        tv = self.t_views
        t_seen = self.t_grid[jm] + s - _weight_centroid(s, calib.tau_s)
        lam = np.clip((t_seen - tv[jm]) / np.maximum(tv[jm + (jj > 0)] - tv[jm], 1e-12), 0.0, 1.0)
        # a row read at a node takes the whole step: its view is V_j whatever the τ
        lam = np.where(s >= self.h_steps[jm] * (1 - 1e-9), 1.0, lam)
        share = np.where(jj > 0, share, 0.0)
        return (np.ascontiguousarray(jj, np.int64), np.ascontiguousarray(share, np.float32),
                np.ascontiguousarray(lam, np.float32))

    def _alphas(self, calib: Calibration) -> np.ndarray:
        """α_j = 1 − e^{−h_j/τ} of every step j ≥ 1 (index 0: the initial state), float32."""
        return np.r_[1.0, iir_alpha(self.h_steps, calib.tau_s)].astype(np.float32)

    # ------------------------------------------------------------------ detector
    def predict_raw(self, calib: Calibration):
        """IIR-weighted view and support per frame before normalisation: (num, weight) [n, h, w]."""
        V, M = self.views(calib)
        n = len(self.frame_t)
        num = np.empty((n, self.h, self.w), np.float32)
        wgt = np.empty_like(num)
        if n:
            jj, share, lam = self._row_steps(calib)
            self.work += len(V) * self.h * self.w
            _iir_rows(V, M, self._alphas(calib), jj, share, lam, num, wgt)
        return num, wgt

    def predict(self, calib: Calibration, extra_psf_px: float = 0.0, valid_min: float = 0.99):
        """Predicted frames (float32 [n, h, w], counts, FPN included) and their valid mask (bool).

        Eq. 10/11: B_j = B_{j−1} + α (V_j − B_{j−1}), α = 1 − exp(−Δt/τ), over the fine grid;
        each frame row is the state at its read time (linear between grid points). A pixel is
        valid when ≥ `valid_min` of its exponential weight came from known reference (inside the
        canvas and its support).
        """
        num, m = self.predict_raw(calib)
        n = len(num)
        valid = m >= valid_min
        # Normalised by the known weight, so pixels near the edge stay in range (they are invalid).
        out = np.empty_like(num)
        out[...] = self.reference_view[None]
        np.divide(num, m, out=out, where=m > 0.5)
        if extra_psf_px > 0:
            g = self._psf_kernel(extra_psf_px)
            for k in range(n):
                out[k] = cv2.sepFilter2D(out[k], -1, g, g, borderType=cv2.BORDER_REPLICATE)
        if self.fpn is not None:
            out += self.fpn[None]
        return out, valid

    def _psf_kernel(self, extra_psf_px: float) -> np.ndarray:
        s = float(extra_psf_px) * self.scale
        return cv2.getGaussianKernel(2 * int(math.ceil(4 * s)) + 1, s, cv2.CV_32F)   # ±4σ, sums to 1

    def adjoint(self, calib: Calibration, cotangent: np.ndarray, extra_psf_px: float = 0.0,
                weight: np.ndarray | None = None) -> np.ndarray:
        """Aᵀ c: the canvas gradient of Σ c·prediction (float64, canvas shape), for least squares on the
        reference. The prediction is linear in the canvas: views (interpolation taps), IIR, the
        normalisation by `weight` (the known-support weight of `predict_raw`, fixed) and the extra PSF
        (symmetric, so its own adjoint)."""
        c = np.asarray(cotangent, np.float32)
        if extra_psf_px > 0:
            g = self._psf_kernel(extra_psf_px)
            c = np.stack([cv2.sepFilter2D(x, -1, g, g, borderType=cv2.BORDER_CONSTANT) for x in c])
        if weight is not None:
            c = np.where(weight > 0.5, c / np.maximum(weight, 0.5), 0.0).astype(np.float32)
        grad = np.zeros(self.reference.shape, np.float64)
        if len(c):
            jj, share, lam = self._row_steps(calib)
            Hs = np.ascontiguousarray(self.homographies(calib, self.t_views))
            self.work += (1 + WARP_COST) * len(Hs) * self.h * self.w   # the IIR back, the taps scattered
            _adjoint_rows(np.ascontiguousarray(c), self._alphas(calib), jj, share, lam, Hs,
                          self.origin[0], self.origin[1], self._cubic, grad)
        return grad


def predict_frames(reference, frame_t, gyro_t, gyro_rate, calib: Calibration, *, t_ref: float,
                   scale: float = 1.0, extra_psf_px: float = 0.0, fpn=None, max_step_px: float = 0.5):
    """One-shot `ForwardModel(...).predict(calib, extra_psf_px)`: (frames float32 [n,h,w], valid bool)."""
    fm = ForwardModel(reference, frame_t, gyro_t, gyro_rate, calib, t_ref=t_ref, scale=scale, fpn=fpn,
                      max_step_px=max_step_px, cache_mb=0)
    return fm.predict(calib, extra_psf_px)
