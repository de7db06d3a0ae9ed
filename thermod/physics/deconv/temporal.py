"""Temporal deconvolution: frame t restored from frames t−N…t, each warped into t's geometry by the
gyro rotation (rolling readout included, Eq. 16) and each with its own blur kernel.

The warped views share one unknown and differ in kernel and noise, so K&F over all of them (one data
term per view) keeps the closed-form x-step with sums over the views:

    X = (Σ_j K̄_j D_j + (β/λ') F(∇ᵀw)) / (Σ_j |K_j|² + (β/λ')(|F∂x|² + |F∂y|²))

The frequencies one comet kernel nulls are kept by another's, and the views' noise averages;
λ' = `LAM_SCALE` · λ(σ̂ of frame t).

The rule it keeps: a neighbour enters only where it agrees with frame t's own solve x₀. Its misfit
to k_j ⊛ x₀ (`WINDOW_PX` box, FFC offset removed) against frame t's misfit plus twice its noise
gives a weight (`DATA_DISAGREE`), times the warped support; weights enter by filling with the
prediction, and the result is blended with x₀ by the mean weight, so where no neighbour agreed the
output is x₀ itself. A view below `MIN_VIEW_WEIGHT` in a tile, or one the gyro does not reach, is
left out. Kernel grids are solved in cells with `JOINT_MARGIN_PX`. The derivation and the cost per
frame (`last_fft_pairs`): docs/design.md §1.5, "Temporal deconvolution, the joint solve".
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from thermod.physics.geometry import integrate_rotations, jit_cores, trapezoid_step_into

from .checks import DeconvError, check_frame, check_image, check_kernel
from .noise import noise_sigma, value_range_of
from .solver import TILE_OVERLAP, Deconvolver
from .tiles import TILE_MARGIN_PX
from .wstep import LUT_SIZE, LUT_VMAX, wstep_div
from .xstep import finish, prepare, wiener_solve, xstep

DEFAULT_VIEWS = 6          # frame t and its five predecessors
LAM_SCALE = 1.0            # joint λ / single-frame λ (0.7 and 1.5 measured lower, bench_temporal --lam-scale)
WINDOW_PX = 9              # box of the local mean square misfit
DATA_DISAGREE = (1.5, 3.0)  # neighbour's misfit / frame t's (+ 2σ̂²): full weight below, none above
MIN_VIEW_WEIGHT = 0.5      # a view below this share of its support in a tile is dropped there
SUPPORT_INSET_PX = 2       # warped support shrunk by this much (interpolation at the edge)
# tile margin of the joint solve under a kernel grid: the views' long comets wrap at tile edges (8 px
# lost 0.3 dB at 100 °/s; 48 px gained 0.06 dB more for 1.8× the points; coarser 4×6 tiles with
# 32 px lost up to 0.5 dB under roll, bench_temporal)
JOINT_MARGIN_PX = 24
MAP_STEP_PX = 8            # the warp is solved every 8 px and interpolated bilinearly (it is smooth)


@dataclass(frozen=True)
class PastFrame:
    """One frame of the history: the frame as read (float32 counts), its kernel (`Kernel` or
    `KernelGrid`) and its read time (camera clock, s, last row)."""

    frame: np.ndarray
    kernel: object
    t_frame: float


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
    out = np.empty((len(times), 3, 3))
    _orientations_at(tc, np.ascontiguousarray(w), Q, times, out)
    return out


jit_cores()   # the geometry's trapezoid step, callable from the jitted code below


@njit(cache=True, nogil=True)
def _orientations_at(tc, w, Q, times, out):
    """out[k] = Q[j] · exp([½(ω_j + ω(s)) (s − t_j)]×) at s = times[k], t_j the last sample at or before
    s (the first before them all), ω(s) interpolated linearly and held beyond the samples: the
    integrator's trapezoid step from the sample to s."""
    n = tc.shape[0]
    E = np.empty((3, 3))
    ws = np.empty(3)
    for k in range(times.shape[0]):
        s = times[k]
        j = np.searchsorted(tc, s, side="right") - 1
        if j < 0:
            j = 0
        if s <= tc[0]:
            ws[:] = w[0]
        elif j >= n - 1:
            j = n - 1
            ws[:] = w[n - 1]
        else:
            f = (s - tc[j]) / (tc[j + 1] - tc[j])
            for a in range(3):
                ws[a] = w[j, a] + f * (w[j + 1, a] - w[j, a])
        trapezoid_step_into(Q[j], w[j], ws, s - tc[j], E, out[k])


@njit(cache=True, nogil=True)
def _rolling_maps(xs, ys, P, B, mx, my):
    """mx, my [len(ys), len(xs)]: where pixel q = (xs[c], ys[r]) of frame t lies in frame j:
    π(B[y'] P[r] q), with P[r] = R_t(ys[r]) K⁻¹ (that row of t seen at its read time) and
    B[y'] = K R_j(y')ᵀ for every source row y'; y' by fixed-point iteration (first guess y' = ys[r])."""
    H = B.shape[0]
    for r in range(ys.shape[0]):
        y = ys[r]
        for c in range(xs.shape[0]):
            x = xs[c]
            d0 = P[r, 0, 0] * x + P[r, 0, 1] * y + P[r, 0, 2]
            d1 = P[r, 1, 0] * x + P[r, 1, 1] * y + P[r, 1, 2]
            d2 = P[r, 2, 0] * x + P[r, 2, 1] * y + P[r, 2, 2]
            yy = min(max(int(round(y)), 0), H - 1)
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
            mx[r, c] = px
            my[r, c] = py


def coarse_warp_maps(calib, gyro_t, gyro_rate, t_dst: float, t_src: float):
    """(map_x, map_y) float64 on the grid of every `MAP_STEP_PX`-th row and column of frame `t_dst`
    (Eq. 16 per row pair, rolling readout: where those pixels lie in frame `t_src`), or None
    without gyro coverage of both frames. Grid node (r, c) is pixel (r·step, c·step)."""
    H, W = int(calib.height), int(calib.width)
    step = MAP_STEP_PX
    ys = np.arange(0, H - 1 + step, step, dtype=np.float64)
    xs = np.arange(0, W - 1 + step, step, dtype=np.float64)
    ro = float(calib.readout_s)
    s_dst = t_dst - ro * (1.0 - (ys + 1.0) / H)
    s_src = t_src - ro * (1.0 - (np.arange(H) + 1.0) / H)
    # without a rolling readout every row shares its frame's read time: two orientations, not H + rows
    times, back = np.unique(np.r_[s_dst, s_src], return_inverse=True)
    R = camera_orientations(gyro_t, gyro_rate, calib, t_dst, times)
    if R is None:
        return None
    R = R[back]
    K = np.asarray(calib.K, np.float64)
    P = np.ascontiguousarray(R[:len(ys)] @ np.linalg.inv(K))
    B = np.ascontiguousarray(K @ np.transpose(R[len(ys):], (0, 2, 1)))
    cx = np.empty((len(ys), len(xs)))
    cy = np.empty((len(ys), len(xs)))
    _rolling_maps(xs, ys, P, B, cx, cy)
    return cx, cy


def warp_maps(calib, gyro_t, gyro_rate, t_dst: float, t_src: float):
    """(map_x, map_y) float32 [H, W] for cv2.remap of frame `t_src` into frame `t_dst`'s pixels
    (Eq. 16 per row pair, rolling readout), or None without gyro coverage of both frames."""
    coarse = coarse_warp_maps(calib, gyro_t, gyro_rate, t_dst, t_src)
    if coarse is None:
        return None
    H, W = int(calib.height), int(calib.width)
    step = MAP_STEP_PX
    # bilinear up-sampling: pixel (y, x) reads the coarse grid at (y / step, x / step)
    up = np.float64([[1.0 / step, 0.0, 0.0], [0.0, 1.0 / step, 0.0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    mx = cv2.warpAffine(coarse[0].astype(np.float32), up, (W, H), flags=flags,
                        borderMode=cv2.BORDER_REPLICATE)
    my = cv2.warpAffine(coarse[1].astype(np.float32), up, (W, H), flags=flags,
                        borderMode=cv2.BORDER_REPLICATE)
    return mx, my


def warp(img: np.ndarray, maps, interpolation: int = cv2.INTER_CUBIC) -> np.ndarray:
    """`img` resampled at `maps` (float32; beyond its edges replicated: `warped_support` says where)."""
    return cv2.remap(np.asarray(img, np.float32), maps[0], maps[1], interpolation,
                     borderMode=cv2.BORDER_REPLICATE)


def warped_support(maps, shape, inset: int = SUPPORT_INSET_PX) -> np.ndarray:
    """1 where the map lands at least `inset` px inside the source frame, else 0 (float32)."""
    H, W = shape
    mx, my = maps
    ok = (mx >= inset) & (mx <= W - 1 - inset) & (my >= inset) & (my <= H - 1 - inset)
    return ok.astype(np.float32)


def _kernel_of(kernel, y: float, x: float):
    """The kernel at pixel (y, x): a grid's cell there, or the one kernel."""
    if hasattr(kernel, "kernels"):
        return kernel.kernel_at(y, x)
    return kernel


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
    """Per-frame temporal deconvolution over a history of the last `views` − 1 frames.

    Call `run(frame, kernel, t_frame, gyro_t, gyro_rate)` once per frame, in read order. It solves
    the frame alone with `single` (x₀: today's single-frame result, also `last_single`), then
    jointly with the history's frames, and appends the frame to the history (`history`, a deque of
    `PastFrame`). `solve` + `push` split it for callers that keep the ring themselves (several
    worker threads, one TemporalDeconvolver each, sharing one ordered ring).

    Parameters
    ----------
    calib : the Calibration (intrinsics, readout, gyro → camera) the frames and kernels share.
    views : frames per solve, frame t included (1: the single-frame solve alone).
    single : the `Deconvolver` of the single-frame solves (default: K&F, its defaults). The joint
        solve shares its method, α, λ rule, FFT plans and OTF cache (one instance per thread).
    lam_scale : joint λ' = lam_scale · λ of frame t.
    iterations : K&F β steps of the joint solve (None: the single solve's).
    max_age_s : history frames older than this (camera clock) are dropped.
    min_coverage : a history frame whose kernel's gyro coverage is below this is not used.
    interpolation : cv2 interpolation of the warps (cubic: linear lost 0.1 dB on high-SNR scenes).
    overlap, uniform_tol_px : as `Deconvolver.run_varying` (a kernel grid).
    """

    def __init__(self, calib, views: int = DEFAULT_VIEWS, single: Deconvolver | None = None, *,
                 lam_scale: float = LAM_SCALE, iterations: int | None = None, max_age_s: float = 0.25,
                 min_coverage: float = 0.99, interpolation: int = cv2.INTER_CUBIC,
                 overlap: float = TILE_OVERLAP, uniform_tol_px: float = 0.5):
        if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or not 1 <= views <= 16:
            raise DeconvError(f"views: expected an integer in [1, 16], got {views!r}")
        lam_scale = float(lam_scale)
        if not (lam_scale > 0 and math.isfinite(lam_scale)):
            raise DeconvError(f"lam_scale: expected a positive factor, got {lam_scale}")
        if single is not None and not isinstance(single, Deconvolver):
            raise DeconvError(f"single: expected a Deconvolver, got {type(single).__name__}")
        max_age_s = float(max_age_s)
        if not max_age_s > 0:
            raise DeconvError(f"max_age_s: expected a positive age (s), got {max_age_s}")
        self.calib = calib
        self.views = int(views)
        self.single = single or Deconvolver()
        self.lam_scale = lam_scale
        self.max_age_s = max_age_s
        self.min_coverage = float(min_coverage)
        self.interpolation = interpolation
        self.overlap, self.uniform_tol_px = float(overlap), float(uniform_tol_px)
        s = self.single
        ref = s if iterations is None else Deconvolver(method=s.method, alpha=s.alpha, iterations=iterations)
        self._steps = list(zip(ref._betas, ref._luts, ref._taus, strict=True))
        self.history: deque[PastFrame] = deque(maxlen=max(self.views - 1, 1))
        # what the last `run` did, for the caller's books
        self.last_views = 1            # frames that entered the joint solve (1: the single solve alone)
        self.last_weights: list[float] = []   # each neighbour's mean data weight (0: dropped)
        self.last_fft_pairs_single = 0.0   # frame-sized FFT pairs of the single-frame solve
        self.last_fft_pairs = 0.0      # … of the whole `run`
        self.last_single: np.ndarray | None = None
        self.last_seconds = (0.0, 0.0)       # (single solve, temporal part) wall time
        self.last_cpu_seconds = (0.0, 0.0)   # the same in process CPU time

    def reset(self) -> None:
        """Forget the history (a discontinuity the caller knows of: a restart, a seek, a new NUC table)."""
        self.history.clear()

    # ------------------------------------------------------------------ per frame
    def run(self, frame: np.ndarray, kernel, t_frame: float, gyro_t, gyro_rate, *,
            value_range: tuple[float, float] | None = None) -> np.ndarray:
        """`solve` the frame with the object's own history, then `push` it (one caller, read order)."""
        out = self.solve(frame, kernel, t_frame, gyro_t, gyro_rate, self.history, value_range=value_range)
        self.push(frame, kernel, t_frame)
        return out

    def push(self, frame: np.ndarray, kernel, t_frame: float) -> None:
        """Append a frame (as read, with its kernel and read time) to the history, dropping frames
        older than `max_age_s`. Frames must come in read order; a frozen (FFC) frame must not."""
        img = np.array(check_image(frame), np.float32)   # a copy: the caller may reuse its buffer
        t_frame = float(t_frame)
        if self.history and not t_frame > self.history[-1].t_frame:
            raise DeconvError(f"t_frame: {t_frame} is not after the history's last frame "
                              f"({self.history[-1].t_frame}); frames must come in read order")
        while self.history and t_frame - self.history[0].t_frame > self.max_age_s:
            self.history.popleft()
        if self.views > 1:
            self.history.append(PastFrame(img, kernel, t_frame))

    def solve(self, frame: np.ndarray, kernel, t_frame: float, gyro_t, gyro_rate, history=(), *,
              value_range: tuple[float, float] | None = None) -> np.ndarray:
        """Restore `frame` (counts, calibration-sized) read at `t_frame` (camera clock, last row) with
        its `kernel` (Kernel or KernelGrid), jointly with the newest `views` − 1 frames of `history`
        (`PastFrame`s read before it, any order; nothing is stored: a thread-safe core for callers
        that keep their own ring). Returns float32 counts.

        `gyro_t`, `gyro_rate`: raw gyro samples (as for the kernel renderers; a ring buffer may be
        passed whole) spanning the history's frames — a frame they do not reach is left out.
        """
        img, t_frame = check_frame(frame, self.calib, t_frame)
        t0, c0 = time.perf_counter(), time.process_time()
        lo, hi = value_range_of(img, value_range)
        grid = hasattr(kernel, "kernels")
        if grid:
            x0 = self.single.run_varying(img, kernel, overlap=self.overlap,
                                         uniform_tol_px=self.uniform_tol_px, value_range=(lo, hi))
        else:
            x0 = self.single.run(img, kernel, value_range=(lo, hi))
        lam, cells = self.single.last_lam, self.single.last_cells
        t1, c1 = time.perf_counter(), time.process_time()
        self.last_single = x0
        self._count_single(img.shape, kernel, grid, cells)
        self._sigma = noise_sigma(img, (lo, hi))
        past = sorted((p for p in history if p.t_frame < t_frame), key=lambda p: p.t_frame)
        newest = past[-(self.views - 1):] if self.views > 1 else []
        neighbours = self._neighbours(img, t_frame, gyro_t, gyro_rate, newest)
        out = x0
        self.last_weights = []
        if neighbours:
            weights = np.zeros(len(neighbours))
            out = self._joint(img, kernel, x0, neighbours, lo, hi, lam * self.lam_scale, grid and cells > 1,
                              weights)
            self.last_weights = [float(w) for w in weights]
        self.last_views = 1 + sum(w > 0 for w in self.last_weights)
        self.last_seconds = (t1 - t0, time.perf_counter() - t1)
        self.last_cpu_seconds = (c1 - c0, time.process_time() - c1)
        return out

    def _count_single(self, shape, kernel, grid, cells) -> None:
        k0 = kernel.kernel_at((shape[0] - 1) / 2, (shape[1] - 1) / 2) if grid else kernel
        fp = self.single.padded_shape(shape, check_kernel(k0)[0].shape)
        self._frame_points = fp[0] * fp[1]
        steps = len(self.single._betas) if self.single.method == "kf" else 0
        if grid and cells > 1:
            centers = np.asarray(kernel.centers, np.float64)
            lay = self.single._layout(shape, centers, self.overlap, TILE_MARGIN_PX)
            self.last_fft_pairs = (steps + 1) * cells * lay.pshape[0] * lay.pshape[1] / self._frame_points
        else:
            self.last_fft_pairs = float(steps + 1)
        self.last_fft_pairs_single = self.last_fft_pairs

    def _neighbours(self, img, t_frame, gyro_t, gyro_rate, history) -> list:
        """[(warped frame, warped support, kernel, maps)] of the usable history frames, newest first."""
        out = []
        for past in reversed(history):
            if t_frame - past.t_frame > self.max_age_s or past.t_frame >= t_frame:
                continue
            if getattr(past.kernel, "coverage", 1.0) < self.min_coverage:
                continue
            maps = warp_maps(self.calib, gyro_t, gyro_rate, t_frame, past.t_frame)
            if maps is None:
                continue
            support = warped_support(maps, img.shape)
            if support.mean() < 0.02:
                continue
            out.append((warp(past.frame, maps, self.interpolation), support, past.kernel, maps))
        return out

    # ------------------------------------------------------------------ joint solve
    def _joint(self, img, kernel, x0, neighbours, lo, hi, lam, tiled, weights) -> np.ndarray:
        h, wd = img.shape
        if not tiled:
            k0 = kernel.kernel_at((h - 1) / 2, (wd - 1) / 2) if hasattr(kernel, "kernels") else kernel
            x = self._solve_box(img, x0, (0, h, 0, wd), k0, neighbours, lo, hi, lam, None, weights)
            out = np.empty((h, wd), np.float32)
            finish(x, h, wd, np.float32(lo), np.float32(hi - lo), out)
            return out
        centers = np.asarray(kernel.centers, np.float64)
        lay = self.single._layout(img.shape, centers, self.overlap, JOINT_MARGIN_PX)
        out = np.zeros((h, wd), np.float32)
        share = np.zeros(len(neighbours))
        for t in range(len(lay.boxes)):
            r, c = int(lay.rows[t]), int(lay.cols[t])
            box = tuple(int(v) for v in lay.boxes[t])
            x = self._solve_box(img, x0, box, kernel.kernels[r][c], neighbours, lo, hi, lam, lay.pshape,
                                share)
            weights += share / len(lay.boxes)
            y0, _, xa, _ = box
            ys, ye, xs, xe = (int(v) for v in lay.supports[t])
            v = x[ys - y0:ye - y0, xs - xa:xe - xa] * np.float32(hi - lo) + np.float32(lo)
            out[ys:ye, xs:xe] += v * lay.wy[r, :ye - ys, None] * lay.wx[c, None, :xe - xs]
        return out

    def _solve_box(self, img, x0, box, k0, neighbours, lo, hi, lam, pshape, weights) -> np.ndarray:
        """The joint solve of img[box]: the plan's padded unit-range solution buffer. Writes each
        neighbour's mean data weight over the box into `weights`."""
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
        tile = np.empty((hh, ww), np.float32)
        evidence = np.zeros((hh, ww), np.float32)
        # frame t: its own data (periodic extension as in the single solve) and its misfit to x₀,
        # which absorbed part of its noise: an agreeing neighbour's misfit is that plus 2σ̂²
        K, K2 = otfs[0]
        _predict(K, X0, plan.norm, plan.cin)
        ref = _misfit(img, plan.inv(), y0, xa, hh, ww, lo32, scale)
        ref += np.float32(max(2.0 * self._sigma * self._sigma, 1e-12))
        prepare(img, y0, xa, hh, ww, lo32, scale, plan.rin)
        _acc_view(K, K2, plan.fwd(), kty, k2)
        dlo, dhi = DATA_DISAGREE
        for j, ((wj, support, _, _), (K, K2)) in enumerate(zip(neighbours, otfs[1:], strict=True)):
            _predict(K, X0, plan.norm, plan.cin)
            p = plan.inv()
            sup = support[y0:y1, xa:xb]
            # an FFC step (or drift) offsets the neighbour's counts: its median misfit is removed
            lo_j = lo32
            ok = sup[::3, ::3] > 0
            if ok.any():
                r = (wj[y0:y1:3, xa:xb:3] - lo32) * scale - p[:hh:3, :ww:3]
                lo_j = np.float32(lo32 + float(np.median(r[ok])) / scale)
            e = _misfit(wj, p, y0, xa, hh, ww, lo_j, scale)
            m = sup * np.clip((dhi * ref - e) / ((dhi - dlo) * ref), 0.0, 1.0)
            if float(m.mean()) < MIN_VIEW_WEIGHT * float(sup.mean()):
                m[:] = 0.0   # mostly limited by registration or the model, not noise: not worth it
            weights[j] = float(m.mean())
            evidence += m
            _fill(wj[y0:y1, xa:xb], p[:hh, :ww], np.ascontiguousarray(m, np.float32), lo_j, scale, tile)
            prepare(tile, 0, 0, hh, ww, np.float32(0.0), np.float32(1.0), plan.rin)
            _acc_view(K, K2, plan.fwd(), kty, k2)
        prepare(img, y0, xa, hh, ww, lo32, scale, plan.rin)   # K&F starts from frame t, as the single solve
        if dec.method == "wiener":
            wiener_solve(kty, k2, plan.g2, np.float32(1.0 / lam), plan.norm, plan.cin)
            x = plan.inv()
            steps = 0.5
        else:
            x = self._kf(plan, kty, k2, lam)
            steps = len(self._steps)
        # where no neighbour agreed the joint solution is x₀ under a weaker prior: return x₀ there
        b = cv2.blur(evidence * np.float32(1.0 / len(neighbours)), (WINDOW_PX, WINDOW_PX))
        x[:hh, :ww] = b * x[:hh, :ww] + (1 - b) * ((x0[y0:y1, xa:xb] - lo32) * scale)
        pairs = 0.5 + 1.5 * len(kernels) + steps
        self.last_fft_pairs += pairs * plan.shape[0] * plan.shape[1] / self._frame_points
        return x

    def _kf(self, plan, kty, k2, lam) -> np.ndarray:
        """K&F's continuation (`Deconvolver._kf_steps`) with the joint Σ K̄D and Σ|K|²."""
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


__all__ = ["DEFAULT_VIEWS", "PastFrame", "TemporalDeconvolver", "camera_orientations", "warp", "warp_maps",
           "warped_support"]
