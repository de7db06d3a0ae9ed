"""Temporal deconvolution: frame t restored from frames t−N…t, each warped into t's geometry by the
gyro rotation and each with its own blur kernel.

Model. Frame j is its sharp view blurred by its own kernel, ``y_j = k_j ⊛ S_j + n_j``, and for a
distant scene S_j(p) = S_t(π(H p)) with H = K R(s_t)ᵀ R(s_j) K⁻¹ (Eq. 16), s the read time of the
pixel's row (rolling readout). Warped into t's pixels (`warp_maps`, cv2.remap), ``w_j ≈ k_j ⊛ S_t
+ n_j``: the views share one unknown and differ in kernel and noise. K&F over all of them
(K&F Eq. 1 with one data term per view) keeps the closed-form x-step, with the sums over views::

    X = (Σ_j K̄_j D_j + (β/λ') F(∇ᵀw)) / (Σ_j |K_j|² + (β/λ')(|F∂x|² + |F∂y|²))

so the frequencies one comet kernel nulls are filled by another's, and the noise of N views
averages. λ' = `lam_scale` · λ(σ̂ of frame t).

Where a view disagrees with frame t (a moving hot object, parallax, new scene at the borders, an
FFC offset step, a rotation without gyro coverage) its data must not enter. The test is in the
sharp domain, where it is local: the single-frame solve x₀ of frame t against the neighbour's own
single-frame solve x̂_j (kept in the history) warped into t. After removing their median offset
(an FFC step), the local mean square difference (`WINDOW_PX` box) is compared with its median over
the frame (the agreement level, floored by the estimates' own noise): a weight 1 below
`DISAGREE` (lo) times it, 0 above (hi). A sharp-domain fault at q corrupts the data at q + u for
every u in k_j's support, so the data weight is 1 − min(1, `SPREAD_GAIN` · k_j ⊛ (1 − m)), times
the warped support. A view whose median disagreement exceeds `GLOBAL_DISAGREE` times the noise floor
is dropped whole.

Weights enter without breaking the Fourier solve by filling (EM-style): the view's data becomes
``d_j = m_j w_j + (1 − m_j)(k_j ⊛ x₀)``, computed in the same padded domain as the solve, so
where m_j = 0 the view says exactly what frame t's own solve says and adds no new information.

A kernel grid (roll) is solved in the tiles of `Deconvolver.run_varying` (its layout, FFT size and
blend), each view with its kernel at the tile's centre mapped into that view.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from thermod.physics.geometry import integrate_rotations, so3_exp_many

from .checks import DeconvError, check_image, check_kernel
from .noise import noise_sigma, value_range_of
from .solver import TILE_OVERLAP, Deconvolver
from .tiles import TILE_MARGIN_PX, kernel_spread
from .wstep import LUT_SIZE, LUT_VMAX, wstep_div
from .xstep import finish, prepare, wiener_solve, xstep

DEFAULT_VIEWS = 6          # frame t and its five predecessors
WINDOW_PX = 9              # box of the local mean square disagreement
DISAGREE = (1.5, 3.0)      # local disagreement / its reference: full weight below, none above
GLOBAL_DISAGREE = 30.0     # a view whose median disagreement is this × the noise floor is dropped
SPREAD_GAIN = 4.0          # data weight falls to 0 once a quarter of a pixel's kernel sees a fault
SUPPORT_INSET_PX = 2       # warped support shrunk by this much (interpolation at the edge)
LAM_SCALE = 1.0
SHARP_TEST = False
JOINT_UNIFORM_TOL_PX = 0.5  # a grid within this of uniform is solved jointly as one tile (its centre kernel)
MIN_VIEW_WEIGHT = 0.5      # a view whose data weight in a tile falls below this share of its support is left out
BLEND = True
DATA_DISAGREE = (1.5, 3.0)  # a neighbour's local misfit to x₀ / frame t's: full weight below, none above
JOINT_MARGIN_PX = 24       # tile margin of the joint solve: its views wrap long comets at the tile edges
EDGE_EXEMPT_PX = 3         # frame t's border band where x₀, not the neighbour, is suspect
PAD_SELF = False
PAD_PRED = False
LEVEL_PERCENTILE = 20.0    # the agreement level: this percentile of the local disagreement
EDGE_PX = 0.2              # registration/artefact tolerance at edges: a shift of this many px


@dataclass(frozen=True)
class PastFrame:
    """One frame of the history: the frame as read (counts), its kernel (`Kernel` or `KernelGrid`),
    its read time (camera clock, s, last row) and its single-frame estimate (counts)."""

    frame: np.ndarray
    kernel: object
    t_frame: float
    estimate: np.ndarray


# ---------------------------------------------------------------------------------- geometry
def camera_orientations(gyro_t, gyro_rate, calib, t_ref: float, times) -> np.ndarray | None:
    """R(t_ref)ᵀ R(s) for every camera time s in `times` [n] from raw gyro samples (the calibration
    maps them to camera rates and clock); None when the gyro does not span [min(times), t_ref]."""
    times = np.asarray(times, np.float64)
    lo, hi = float(min(times.min(), t_ref)), float(max(times.max(), t_ref))
    t, r = calib.condition_window(gyro_t, gyro_rate, lo, hi)
    t = np.asarray(t, np.float64)
    if len(t) < 2:
        return None
    tc = t + calib.time_offset_s
    step = 2.0 / calib.rate_hz
    if tc[0] > lo + step or tc[-1] < hi - step:
        return None
    i0, i1 = np.searchsorted(tc, [lo - step, hi + step])
    i0, i1 = max(int(i0) - 1, 0), min(int(i1) + 1, len(tc))
    tc = tc[i0:i1]
    w = (np.asarray(r, np.float64)[i0:i1] - np.asarray(calib.bias_rad_s)) @ calib.gyro_to_camera_matrix.T
    Q = integrate_rotations(tc, w, t_ref)
    j = np.clip(np.searchsorted(tc, times, side="right") - 1, 0, len(tc) - 1)
    ws = np.stack([np.interp(times, tc, w[:, a]) for a in range(3)], axis=1)
    E = so3_exp_many(0.5 * (w[j] + ws) * (times - tc[j])[:, None])
    return np.einsum("nij,njk->nik", Q[j], E)


@njit(cache=True, nogil=True)
def _rolling_maps(P, B, mx, my):
    """mx, my [H, W]: where output pixel q = (x, y) of frame t lies in frame j: π(B[y'] P[y] q), with
    P[y] = R_t(y) K⁻¹ (row y of t seen at its read time) and B[y'] = K R_j(y')ᵀ; the source row y'
    from one fixed-point pass (first guess y' = y)."""
    H, W = mx.shape
    for y in range(H):
        for x in range(W):
            d0 = P[y, 0, 0] * x + P[y, 0, 1] * y + P[y, 0, 2]
            d1 = P[y, 1, 0] * x + P[y, 1, 1] * y + P[y, 1, 2]
            d2 = P[y, 2, 0] * x + P[y, 2, 1] * y + P[y, 2, 2]
            yy = y
            px = -1e6
            py = -1e6
            for _ in range(3):
                h0 = B[yy, 0, 0] * d0 + B[yy, 0, 1] * d1 + B[yy, 0, 2] * d2
                h1 = B[yy, 1, 0] * d0 + B[yy, 1, 1] * d1 + B[yy, 1, 2] * d2
                h2 = B[yy, 2, 0] * d0 + B[yy, 2, 1] * d1 + B[yy, 2, 2] * d2
                if h2 <= 1e-9:
                    px = -1e6
                    py = -1e6
                    break
                px = h0 / h2
                py = h1 / h2
                yn = min(max(int(round(py)), 0), H - 1)
                if yn == yy:
                    break
                yy = yn
            mx[y, x] = px
            my[y, x] = py


def warp_maps(calib, gyro_t, gyro_rate, t_dst: float, t_src: float):
    """(map_x, map_y) float32 [H, W] for cv2.remap of frame `t_src` into frame `t_dst`'s pixels
    (Eq. 16 per row pair, rolling readout), or None without gyro coverage of both frames."""
    H, W = int(calib.height), int(calib.width)
    rows = np.arange(H, dtype=np.float64)
    ro = float(calib.readout_s)
    s_dst = t_dst - ro * (1.0 - (rows + 1.0) / H)
    s_src = t_src - ro * (1.0 - (rows + 1.0) / H)
    R = camera_orientations(gyro_t, gyro_rate, calib, t_dst, np.r_[s_dst, s_src])
    if R is None:
        return None
    mx = np.empty((H, W), np.float32)
    my = np.empty((H, W), np.float32)
    K = np.asarray(calib.K, np.float64)
    P = np.ascontiguousarray(R[:H] @ np.linalg.inv(K))
    B = np.ascontiguousarray(K @ np.transpose(R[H:], (0, 2, 1)))
    _rolling_maps(P, B, mx, my)
    return mx, my


def warp(img: np.ndarray, maps, interpolation: int = cv2.INTER_CUBIC) -> np.ndarray:
    return cv2.remap(np.asarray(img, np.float32), maps[0], maps[1], interpolation,
                     borderMode=cv2.BORDER_REPLICATE)


def warped_support(maps, shape, inset: int = SUPPORT_INSET_PX) -> np.ndarray:
    """1 where the map lands at least `inset` px inside the source frame, else 0 (float32)."""
    H, W = shape
    mx, my = maps
    ok = (mx >= inset) & (mx <= W - 1 - inset) & (my >= inset) & (my <= H - 1 - inset)
    return ok.astype(np.float32)


# ---------------------------------------------------------------------------------- weights
def _kernel_of(kernel, y: float, x: float):
    if hasattr(kernel, "kernels"):
        return kernel.kernel_at(y, x)
    return kernel


def _blur_support(img: np.ndarray, kernel) -> np.ndarray:
    """k ⊛ img (forward model B(p) = Σ_u k(u) img(p − u)), zero outside the frame."""
    w, (oy, ox) = check_kernel(kernel)
    kh, kw = w.shape
    flipped = np.ascontiguousarray(w[::-1, ::-1])
    return cv2.filter2D(img, cv2.CV_32F, flipped, anchor=(kw - 1 - ox, kh - 1 - oy),
                        borderType=cv2.BORDER_CONSTANT)


def agreement_weights(x0: np.ndarray, xj: np.ndarray, support: np.ndarray, kernel_j, noise_floor: float,
                      *, window: int | None = None, disagree=None, global_disagree: float | None = None,
                      spread_gain: float | None = None, edge_px: float | None = None):
    """(data weight [H, W] float32, offset, median disagreement / noise floor) of one neighbour.

    x0: frame t's single-frame estimate; xj: the neighbour's, warped into t (same units); support:
    where the warp lands in the neighbour; noise_floor: the mean square difference expected of two
    agreeing estimates (their noise). The weight is 0 everywhere when the view disagrees globally.
    """
    window = WINDOW_PX if window is None else window
    disagree = DISAGREE if disagree is None else disagree
    global_disagree = GLOBAL_DISAGREE if global_disagree is None else global_disagree
    spread_gain = SPREAD_GAIN if spread_gain is None else spread_gain
    edge_px = EDGE_PX if edge_px is None else edge_px
    ok = support > 0
    if ok.sum() < 0.05 * ok.size:
        return np.zeros_like(support), 0.0, math.inf
    diff = x0 - xj
    offset = float(np.median(diff[ok][::7]))   # FFC offset step (and any slow drift)
    diff -= np.float32(offset)
    # x₀ is at its worst on frame t's outermost pixels (its boundary extension): a difference there
    # is x₀'s error, not the neighbour's, and must not spread (box filter) into a band of lost data
    b = EDGE_EXEMPT_PX
    diff[:b] = 0
    diff[-b:] = 0
    diff[:, :b] = 0
    diff[:, -b:] = 0
    e = cv2.blur(diff * diff, (window, window))
    level = float(np.percentile(e[ok][::7], LEVEL_PERCENTILE))
    ratio = level / max(noise_floor, 1e-12)
    if ratio > global_disagree:
        return np.zeros_like(support), offset, ratio
    # two estimates of one scene differ most at its edges (their different kernels' artefacts, the
    # warp's interpolation, sub-pixel registration): tolerate a shift of `edge_px` there
    gx = cv2.Sobel(x0, cv2.CV_32F, 1, 0, ksize=1)
    gy = cv2.Sobel(x0, cv2.CV_32F, 0, 1, ksize=1)
    g = cv2.blur(gx * gx + gy * gy, (window, window))
    ref = np.float32(max(level, noise_floor)) + np.float32(edge_px * edge_px) * g
    lo, hi = disagree
    m = np.clip((hi * ref - e) / ((hi - lo) * ref), 0.0, 1.0).astype(np.float32)
    m *= support     # outside the support the neighbour's estimate is extrapolated: not evidence
    bad = _blur_support(1.0 - m, kernel_j)
    return (np.clip(1.0 - spread_gain * bad, 0.0, 1.0) * support).astype(np.float32), offset, ratio


# ---------------------------------------------------------------------------------- numba helpers
@njit(cache=True, nogil=True)
def _acc_view(K, K2, D, kty, k2):
    """kty += K̄·D, k2 += |K|² on a half spectrum."""
    h, w = K.shape
    for i in range(h):
        for j in range(w):
            kty[i, j] += K[i, j].conjugate() * D[i, j]
            k2[i, j] += K2[i, j]


@njit(cache=True, nogil=True)
def _predict(K, X, norm, out):
    h, w = K.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = norm * K[i, j] * X[i, j]


@njit(cache=True, nogil=True)
def _fill(w, p, m, lo, scale, out):
    """out = m·(w − lo)·scale + (1 − m)·p over the tile (w in counts, p unit)."""
    h, wd = out.shape
    for i in range(h):
        for j in range(wd):
            mm = m[i, j]
            out[i, j] = mm * (w[i, j] - lo) * scale + (1 - mm) * p[i, j]


def _misfit(data, pred, y0, x0, hh, ww, lo, scale) -> np.ndarray:
    """Local mean square of (data − prediction) over the tile (unit range, `WINDOW_PX` box)."""
    r = (data[y0:y0 + hh, x0:x0 + ww] - lo) * scale - pred[:hh, :ww]
    return cv2.blur(r * r, (WINDOW_PX, WINDOW_PX))


@njit(cache=True, nogil=True)
def _embed(tile, pred, out):
    """out = pred (the padded prediction) with tile written over its top-left corner."""
    hp, wp = out.shape
    hh, ww = tile.shape
    for i in range(hp):
        for j in range(wp):
            out[i, j] = tile[i, j] if i < hh and j < ww else pred[i, j]


# ---------------------------------------------------------------------------------- the solver
class TemporalDeconvolver:
    """Per-frame temporal deconvolution with a history of the last `views` − 1 frames.

    Call `run(frame, kernel, t_frame, gyro_t, gyro_rate)` once per frame, in read order: it solves
    the frame alone (`single`, a `Deconvolver`: the fallback and the estimate kept for the next
    frames' agreement test), then jointly with the frames in the history, and appends the frame.

    Parameters
    ----------
    calib : the Calibration (intrinsics, readout, gyro → camera).
    views : frames per solve, frame t included (1 = the single-frame solve alone).
    single : the `Deconvolver` for the single-frame solves (default: K&F with its defaults); the
        joint solve uses its method, α, λ rule, FFT plans and OTF cache.
    lam_scale : joint data weight λ' = lam_scale · λ of frame t.
    iterations : K&F β steps of the joint solve (None: the single solve's).
    warm_start : the joint K&F starts from x₀ instead of frame t.
    max_age_s : frames older than this (camera clock) are dropped from the history.
    min_coverage : a history frame whose kernel coverage is below this is not used.
    interpolation : cv2 interpolation of the warps.
    overlap, uniform_tol_px : as `Deconvolver.run_varying` (a kernel grid).
    """

    def __init__(self, calib, views: int = DEFAULT_VIEWS, single: Deconvolver | None = None, *,
                 lam_scale: float = LAM_SCALE, iterations: int | None = None, warm_start: bool = False,
                 max_age_s: float = 0.25, min_coverage: float = 0.99,
                 interpolation: int = cv2.INTER_CUBIC, overlap: float = TILE_OVERLAP,
                 uniform_tol_px: float = 0.5):
        if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or not 1 <= views <= 16:
            raise DeconvError(f"views: expected an integer in [1, 16], got {views!r}")
        lam_scale = float(lam_scale)
        if not (lam_scale > 0 and math.isfinite(lam_scale)):
            raise DeconvError(f"lam_scale: expected a positive factor, got {lam_scale}")
        self.calib = calib
        self.views = int(views)
        self.single = single or Deconvolver()
        self.lam_scale = lam_scale
        self.warm_start = bool(warm_start)
        self.max_age_s = float(max_age_s)
        self.min_coverage = float(min_coverage)
        self.interpolation = interpolation
        self.overlap, self.uniform_tol_px = float(overlap), float(uniform_tol_px)
        s = self.single
        betas = list(s._betas)
        if iterations is not None:
            ref = Deconvolver(method=s.method, alpha=s.alpha, iterations=iterations)
            self._steps = list(zip(ref._betas, ref._luts, ref._taus, strict=True))
        else:
            self._steps = list(zip(betas, s._luts, s._taus, strict=True))
        self.history: deque[PastFrame] = deque(maxlen=max(self.views - 1, 1))
        # what the last `run` did, for the caller's books
        self.last_views = 1          # views that entered the joint solve (1: single-frame only)
        self.last_weights: list[float] = []   # mean data weight of each neighbour used
        self.last_fft_pairs_single = 0.0   # of which the single-frame solve
        self.last_fft_pairs = 0.0    # FFT pairs (one forward + one inverse of the solve's size)
        self.last_single: np.ndarray | None = None
        self.last_seconds = (0.0, 0.0)  # (single solve, temporal part) wall time
        self.last_cpu_seconds = (0.0, 0.0)  # the same in process CPU time

    def reset(self) -> None:
        """Forget the history (after a discontinuity the caller knows of: a restart, a seek)."""
        self.history.clear()

    # ------------------------------------------------------------------ per frame
    def run(self, frame: np.ndarray, kernel, t_frame: float, gyro_t, gyro_rate, *,
            value_range: tuple[float, float] | None = None) -> np.ndarray:
        """Restore `frame` (counts) read at `t_frame` with its `kernel` (Kernel or KernelGrid) from it
        and the history; raw gyro samples `gyro_t`, `gyro_rate` must span the history's frames
        (a frame they do not reach is left out). Returns float32 counts; appends the frame."""
        img = check_image(frame)
        if img.shape != (int(self.calib.height), int(self.calib.width)):
            raise DeconvError(f"frame: expected {int(self.calib.height)}×{int(self.calib.width)} "
                              f"(the calibration's), got {img.shape[0]}×{img.shape[1]}")
        t_frame = float(t_frame)
        img = np.asarray(img, np.float32)
        t0, c0 = time.perf_counter(), time.process_time()
        lo, hi = value_range_of(img, value_range)
        grid = hasattr(kernel, "kernels")
        if grid:
            x0 = self.single.run_varying(img, kernel, overlap=self.overlap, uniform_tol_px=self.uniform_tol_px,
                                         value_range=(lo, hi))
        else:
            x0 = self.single.run(img, kernel, value_range=(lo, hi))
        lam = self.single.last_lam
        cells = self.single.last_cells
        t1, c1 = time.perf_counter(), time.process_time()
        self.last_single = x0
        k0 = kernel.kernel_at((img.shape[0] - 1) / 2, (img.shape[1] - 1) / 2) if grid else kernel
        fp = self.single.padded_shape(img.shape, check_kernel(k0)[0].shape)
        self._frame_points = fp[0] * fp[1]
        steps = len(self.single._betas) if self.single.method == "kf" else 0
        if grid and cells > 1:
            lay = self.single._layout(img.shape, np.asarray(kernel.centers, np.float64), self.overlap,
                                      TILE_MARGIN_PX)
            self.last_fft_pairs = (steps + 1) * cells * lay.pshape[0] * lay.pshape[1] / self._frame_points
        else:
            self.last_fft_pairs = float(steps + 1)
        self.last_fft_pairs_single = self.last_fft_pairs
        self._sigma = noise_sigma(img, (lo, hi))
        neighbours = self._neighbours(x0, img, t_frame, lo, hi, gyro_t, gyro_rate)
        self._data_weight = []
        out = x0
        if neighbours:
            tiled = grid and cells > 1 and kernel_spread(kernel) > JOINT_UNIFORM_TOL_PX
            out = self._joint(img, kernel, x0, neighbours, lo, hi, lam, tiled)
        self.last_views = 1 + len(neighbours)
        self.last_seconds = (t1 - t0, time.perf_counter() - t1)
        self.last_cpu_seconds = (c1 - c0, time.process_time() - c1)
        while self.history and t_frame - self.history[0].t_frame > self.max_age_s:
            self.history.popleft()
        if self.views > 1:
            self.history.append(PastFrame(img, kernel, t_frame, x0))
        return out

    def _neighbours(self, x0, img, t_frame, lo, hi, gyro_t, gyro_rate) -> list:
        """[(warped frame, data weight, kernel of the view)] of the usable history frames."""
        self.last_weights = []
        out = []
        if not self.history:
            return out
        rng = hi - lo
        # two agreeing estimates differ by both noises: σ̂ of each (Immerkær), in counts²
        s0 = noise_sigma(x0, (lo, hi)) * rng
        for past in reversed(self.history):
            if t_frame - past.t_frame > self.max_age_s or past.t_frame >= t_frame:
                continue
            cov = getattr(past.kernel, "coverage", 1.0)
            if cov < self.min_coverage:
                continue
            maps = warp_maps(self.calib, gyro_t, gyro_rate, t_frame, past.t_frame)
            if maps is None:
                continue
            support = warped_support(maps, img.shape)
            if not SHARP_TEST:
                if support.mean() < 0.02:
                    continue
                out.append((warp(past.frame, maps, self.interpolation), support, past.kernel, maps))
                self.last_weights.append(float(support.mean()))
                continue
            xj = warp(past.estimate, maps, self.interpolation)
            sj = noise_sigma(past.estimate, (lo, hi)) * rng
            kc = _kernel_of(past.kernel, img.shape[0] / 2, img.shape[1] / 2)
            m, offset, _ = agreement_weights(x0, xj, support, kc, s0 * s0 + sj * sj)
            mean = float(m.mean())
            if mean < 0.02:
                continue
            wj = warp(past.frame, maps, self.interpolation)
            if offset:
                wj += np.float32(offset)
            out.append((wj, m, past.kernel, maps))
            self.last_weights.append(mean)
        return out

    # ------------------------------------------------------------------ joint solve
    def _joint(self, img, kernel, x0, neighbours, lo, hi, lam, tiled) -> np.ndarray:
        dec = self.single
        h, wd = img.shape
        lam_j = lam * self.lam_scale
        if not tiled:
            k0 = kernel
            if hasattr(kernel, "kernels"):   # a grid the single solve found uniform: its central cell
                k0 = kernel.kernel_at((h - 1) / 2, (wd - 1) / 2)
            x = self._solve_box(img, x0, (0, h, 0, wd), k0, neighbours, lo, hi, lam_j, None)
            out = np.empty((h, wd), np.float32)
            finish(x, h, wd, np.float32(lo), np.float32(hi - lo), out)
            return out
        centers = np.asarray(kernel.centers, np.float64)
        lay = dec._layout(img.shape, centers, self.overlap, JOINT_MARGIN_PX)
        out = np.zeros((h, wd), np.float32)
        nr, nc = centers.shape[:2]
        for t in range(len(lay.boxes)):
            r, c = int(lay.rows[t]), int(lay.cols[t])
            box = tuple(int(v) for v in lay.boxes[t])
            x = self._solve_box(img, x0, box, kernel.kernels[r][c], neighbours, lo, hi, lam_j, lay.pshape)
            y0, y1, xa, xb = box
            ys, ye, xs, xe = (int(v) for v in lay.supports[t])
            v = x[ys - y0:ye - y0, xs - xa:xe - xa] * np.float32(hi - lo) + np.float32(lo)
            out[ys:ye, xs:xe] += v * lay.wy[r, :ye - ys, None] * lay.wx[c, None, :xe - xs]
        return out

    def _solve_box(self, img, x0, box, k0, neighbours, lo, hi, lam, pshape) -> np.ndarray:
        """The joint solve of img[box] (unit range; returns the plan's padded solution buffer).

        Every view's padding (beyond the box, up to the FFT size) is its kernel applied to x₀'s
        periodic extension, not a taper of its own data: the views then agree out there (the
        solution's extension is x₀'s) instead of each wrapping its own edges around a long comet.
        """
        dec = self.single
        y0, y1, xa, xb = box
        hh, ww = y1 - y0, xb - xa
        cy, cx = int(round((y0 + y1 - 1) / 2)), int(round((xa + xb - 1) / 2))
        kernels = [k0] + [_kernel_of(kj, float(maps[1][cy, cx]), float(maps[0][cy, cx]))
                          for _, _, kj, maps in neighbours]
        checked = [check_kernel(k) for k in kernels]
        if pshape is None:
            pshape = dec.padded_shape((hh, ww), (max(w.shape[0] for w, _ in checked),
                                                 max(w.shape[1] for w, _ in checked)))
        plan = dec._plan(tuple(pshape))
        lo32, scale = np.float32(lo), np.float32(1.0 / (hi - lo))
        otfs = [dec._otf(plan, w, o) for w, o in checked]   # before any prepare: a miss uses plan.rin
        kty = np.zeros_like(plan.spec)
        k2 = np.zeros(otfs[0][1].shape, np.float32)
        prepare(x0, y0, xa, hh, ww, lo32, scale, plan.rin)
        X0 = plan.fwd().copy()
        pairs = 0.5
        tile = np.empty((hh, ww), np.float32)
        ones = np.ones((hh, ww), np.float32)
        views = [(img, ones)] + [(wj, m[y0:y1, xa:xb]) for wj, m, _, _ in neighbours]
        e0 = None
        evidence = np.zeros((hh, ww), np.float32)
        for v, ((data, mb), (K, K2)) in enumerate(zip(views, otfs, strict=True)):
            _predict(K, X0, plan.norm, plan.cin)
            p = plan.inv()
            if v == 0:
                # frame t's own misfit to x₀ (its noise and x₀'s bias, blurred): the yardstick of a
                # neighbour's misfit, which adds its registration and interpolation errors
                # x₀ was fitted to this very noise, so e₀ understates it: an agreeing neighbour's
                # misfit is e₀ plus its own noise and the part of frame t's that x₀ absorbed
                e0 = _misfit(img, p, y0, xa, hh, ww, lo32, scale)
                e0 += np.float32(max(2.0 * self._sigma * self._sigma, 1e-12))
                prepare(img, y0, xa, hh, ww, lo32, scale, plan.rin)
                _acc_view(K, K2, plan.fwd(), kty, k2)
                pairs += 1.0
                continue
            lo_j = lo32
            if not SHARP_TEST:
                # an FFC step (or drift) offsets the neighbour's counts: measured against x₀'s prediction
                ok = mb[::3, ::3] > 0
                if ok.any():
                    r = (data[y0:y1:3, xa:xb:3] - lo32) * scale - p[:hh:3, :ww:3]
                    lo_j = np.float32(lo32 + float(np.median(r[ok])) / scale)
            ej = _misfit(data, p, y0, xa, hh, ww, lo_j, scale)
            dlo, dhi = DATA_DISAGREE
            mb = mb * np.clip((dhi * e0 - ej) / ((dhi - dlo) * e0), 0.0, 1.0)
            if float(mb.mean()) < MIN_VIEW_WEIGHT * float(views[v][1].mean()):
                # a view that mostly disagrees at the noise level (its registration or the model is
                # the limit, not the noise): its few agreeing pixels are not worth a weaker prior
                mb = np.zeros_like(mb)
            self._data_weight.append(float(mb.mean()))
            evidence += mb
            _fill(data[y0:y1, xa:xb], p[:hh, :ww], np.ascontiguousarray(mb, np.float32), lo_j, scale, tile)
            if PAD_PRED:
                _embed(tile, p, plan.rin)
            else:
                prepare(tile, 0, 0, hh, ww, np.float32(0.0), np.float32(1.0), plan.rin)
            _acc_view(K, K2, plan.fwd(), kty, k2)
            pairs += 1.0
        start = x0 if self.warm_start else img
        prepare(start, y0, xa, hh, ww, lo32, scale, plan.rin)
        if dec.method == "wiener":
            wiener_solve(kty, k2, plan.g2, np.float32(1.0 / lam), plan.norm, plan.cin)
            x = plan.inv()
            pairs += 0.5
        else:
            x = self._kf(plan, kty, k2, lam)
            pairs += len(self._steps)
        if BLEND:
            # where the neighbours said nothing (all filled from x₀), the joint solve is x₀ under a
            # weaker prior, not x₀: return x₀ there, the joint solution where they all agreed
            b = cv2.blur(evidence * np.float32(1.0 / len(neighbours)), (WINDOW_PX, WINDOW_PX))
            x0u = (x0[y0:y1, xa:xb] - lo32) * scale
            x[:hh, :ww] = b * x[:hh, :ww] + (1 - b) * x0u
        self.last_fft_pairs += pairs * plan.shape[0] * plan.shape[1] / self._frame_points
        return x

    def _kf(self, plan, kty, k2, lam) -> np.ndarray:
        x = plan.rin
        alpha = self.single.alpha
        mode = 0 if alpha == 1.0 else 1
        inv_step = np.float32((LUT_SIZE - 1) / LUT_VMAX)
        for beta, lut, tau in self._steps:
            wstep_div(x, mode, np.float32(1.0 / beta), np.float32(tau), lut, inv_step, np.float32(alpha),
                      plan.wx, plan.wy, plan.div, plan.idx)
            xstep(kty, k2, plan.g2, plan.fwd(), np.float32(beta / lam), plan.norm, plan.cin)
            x = plan.inv()
        return x


__all__ = ["DEFAULT_VIEWS", "PastFrame", "TemporalDeconvolver", "agreement_weights", "camera_orientations",
           "kernel_spread", "warp", "warp_maps", "warped_support"]
