"""The deconvolver: K&F half-quadratic splitting (or one Wiener solve) over cached plans and OTFs,
whole-frame or in tiles, and the module-level one-call functions."""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np

from .checks import DeconvError, check_image, check_kernel
from .noise import NOISE_LAMBDA, NoiseLambda, noise_sigma, value_range_of
from .plans import MAX_PLANS, PLANNING_TIMELIMIT_S, Plan, fast_len, place_kernel, pyfftw
from .tiles import TILE_MARGIN_PX, central_cell, moments, stack_kernels, tile_weights
from .wstep import (
    BETA_MAX,
    BETA_RATE,
    BETA_START,
    LUT_SIZE,
    LUT_VMAX,
    beta_schedule,
    shrink_lut,
    shrink_threshold,
    wstep_div,
    wstep_div_stack,
)
from .xstep import (
    blend_stack,
    conj_mul,
    conj_mul_stack,
    finish,
    otf_stack,
    prepare,
    prepare_stack,
    scatter_psfs,
    wiener_solve,
    wiener_stack,
    xstep,
    xstep_stack,
)

DEFAULT_ALPHA = 1.0   # TV: above 2/3 on real thermal scenes at the best λ of each (docs/design.md §1.5)
TILE_OVERLAP = 0.25   # kernel-grid blend ramp: 6×8 at 0.25 beats 3×4 at 1 (benchmarks/results/deconv.md)
# Tiles per stacked FFT call: as many as fit this many FFT points (4 tiles of 128×128 at 640×480 on a
# 6×8 grid; bigger tiles alone): a stack's buffers must stay near the cache (stacks of 2–8 such
# tiles measured alike, all 48 at once slower: benchmarks/results/deconv.md).
TILE_STACK_POINTS = 4 * 128 * 128
SPLIT_OVERLAP = 0.1   # blend ramp of `split` tiles (one kernel: the blend only hides the seams)


class Deconvolver:
    """Reusable deconvolver: caches FFT plans per padded shape and OTFs per (shape, kernel).

    Parameters
    ----------
    method : "kf" (hyper-Laplacian, default) or "wiener" (one Tikhonov solve).
    alpha : prior exponent for "kf": 1 (default, soft threshold), 2/3 (analytic LUT) or any in (0, 1).
    lam : data weight λ for a unit-range frame (K&F convention). None (default): adapted to each
        frame's noise σ̂ (`noise_sigma`) by `lam_rule`.
    lam_rule : the `NoiseLambda` used when lam is None (default: `NoiseLambda.default(method)`).
    fft : "auto" (pyFFTW if installed), "fftw" or "scipy".
    workers : FFT threads (1 = one core; run several Deconvolvers in threads for throughput).
    margin : extra padding (px) beyond the kernel size on each axis before rounding to a fast length.
    iterations : K&F β steps (None: all six): the same continuation from β = 1 towards β_max in n
        coarser steps (n = 3: β = 1, 8, 64). A knob to degrade by under a short time budget: each
        step is one FFT pair and one w-step. 3 steps cost a fraction of a dB; dropping the first
        steps instead costs far more (benchmarks/results/deconv.md, tests/test_deconv.py).
    split : (rows, cols) or None. Solve every uniform-blur frame in rows × cols tiles (blend ramp
        `SPLIT_OVERLAP` of the spacing, `TILE_MARGIN_PX` margins) instead of one frame-sized FFT:
        the faster mode for large sensors, whose frame-sized FFT buffers fall out of cache
        (measured at 1280×1024: benchmarks/results/deconv.md).
    realtime : never stop to measure an FFTW plan (~0.7 s) for an FFT size the saved wisdom lacks:
        estimate it instead (planned in ~1 ms, runs somewhat slower; counted in `estimated_plans`).
        For the daemon's workers, which warm up the common sizes before going live.

    One instance is not thread-safe (it owns its buffers); numba passes and FFTs release the GIL,
    so one instance per thread scales across cores.
    """

    def __init__(self, method: str = "kf", alpha: float = DEFAULT_ALPHA, lam: float | None = None,
                 fft: str = "auto", workers: int = 1, margin: int = 8, cache_size: int = 16,
                 realtime: bool = False, *, lam_rule: NoiseLambda | None = None,
                 iterations: int | None = None, split: tuple[int, int] | None = None):
        if method not in NOISE_LAMBDA:
            raise DeconvError(f"method: expected one of {sorted(NOISE_LAMBDA)}, got {method!r}")
        alpha = float(alpha)
        if not 0 < alpha <= 1:
            raise DeconvError(f"alpha: expected a prior exponent in (0, 1], got {alpha}")
        if lam is not None:
            lam = float(lam)
            if not (lam > 0 and math.isfinite(lam)):
                raise DeconvError(f"lam: expected a positive data weight, got {lam}")
        if fft == "auto":
            fft = "fftw" if pyfftw is not None else "scipy"
        if fft not in ("fftw", "scipy") or (fft == "fftw" and pyfftw is None):
            raise DeconvError(f"fft: expected 'auto', 'scipy' or 'fftw' (pyFFTW installed), got {fft!r}")
        if lam_rule is not None and not isinstance(lam_rule, NoiseLambda):
            raise DeconvError(f"lam_rule: expected a NoiseLambda, got {type(lam_rule).__name__}")
        self.method, self.alpha, self.lam, self.fft = method, alpha, lam, fft
        self.lam_rule = lam_rule or NoiseLambda.default(method, alpha)
        self.last_lam = float("nan")   # λ used for the last frame (adaptive when lam is None)
        self.last_sigma = float("nan")  # the last frame's noise σ̂ (unit range; NaN when lam is fixed)
        self.last_cells = 0   # kernel cells the last frame was solved with (1: one uniform solve)
        self.workers, self.margin, self.cache_size = int(workers), int(margin), int(cache_size)
        self.realtime = bool(realtime)
        # the daemon's plans (measured at warm-up) are time-capped; offline ones are not (plans.py)
        self.planning_limit_s = PLANNING_TIMELIMIT_S if self.realtime else None
        self.estimated_plans = 0
        self._plans: OrderedDict[tuple[int, int], Plan] = OrderedDict()
        self._otfs: OrderedDict = OrderedDict()
        self._layouts: dict = {}
        self._betas = beta_schedule()
        if iterations is not None:
            if (isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer))
                    or not 1 <= iterations <= len(self._betas)):
                raise DeconvError(f"iterations: expected an integer in [1, {len(self._betas)}], "
                                  f"got {iterations!r}")
            # the same continuation from β = 1 towards β_max, in n coarser steps (n = 3: β = 1, 8, 64):
            # keeping the start matters more than the fine steps (dropping the first ones cost more)
            n = int(iterations)
            self._betas = beta_schedule(BETA_START, BETA_MAX, BETA_RATE ** (len(self._betas) / n))[:n]
        self.iterations = len(self._betas)
        if split is not None:
            try:
                split = tuple(int(v) for v in split)
                ok = len(split) == 2 and all(1 <= v <= 16 for v in split)
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise DeconvError(f"split: expected (rows, cols) integers in [1, 16] or None, got {split!r}")
        self.split = split
        if method == "kf" and alpha < 1:
            self._luts = [shrink_lut(alpha, b) for b in self._betas]
            self._taus = [shrink_threshold(alpha, b) for b in self._betas]
        else:
            self._luts = [np.zeros(2, np.float32)] * len(self._betas)
            self._taus = [0.0] * len(self._betas)

    # -------------------------------------------------------------------------- caches
    def padded_shape(self, shape, kshape) -> tuple[int, int]:
        """FFT size for a frame (or tile) of `shape` blurred by a kernel of `kshape`."""
        return (fast_len(shape[0] + kshape[0] + self.margin), fast_len(shape[1] + kshape[1] + self.margin))

    def _plan(self, shape) -> Plan:
        p = self._plans.get(shape)
        if p is None:
            p = self._plans[shape] = Plan(shape, self.fft, self.workers, measure_unseen=not self.realtime,
                                          timelimit_s=self.planning_limit_s)
            self.estimated_plans += p.estimated
            while len(self._plans) > MAX_PLANS:
                self._plans.popitem(last=False)
        else:
            self._plans.move_to_end(shape)
        return p

    def _otf(self, plan: Plan, w: np.ndarray, origin) -> tuple[np.ndarray, np.ndarray]:
        """(K, |K|²) with the kernel's origin moved to index (0, 0), so the output is not displaced."""
        key = (plan.shape, origin, w.shape, hash(w.tobytes()))
        hit = self._otfs.get(key)
        if hit is not None:
            self._otfs.move_to_end(key)
            return hit
        # into the plan's own float32 FFT: a tile solve renders one OTF per tile per frame
        place_kernel(plan.rin, w, origin)
        K = np.array(plan.fwd(), np.complex64)
        K2 = (K.real * K.real + K.imag * K.imag).astype(np.float32)
        self._otfs[key] = (K, K2)
        while len(self._otfs) > self.cache_size:
            self._otfs.popitem(last=False)
        return K, K2

    # -------------------------------------------------------------------------- solvers
    def lam_for(self, img: np.ndarray, lo: float, hi: float) -> float:
        """λ for this frame: the fixed one, or `lam_rule` of the frame's noise."""
        if self.lam is not None:
            self.last_sigma = float("nan")
            return self.lam
        self.last_sigma = noise_sigma(img, (lo, hi))
        return self.lam_rule(self.last_sigma)

    def _solve(self, img, box, w, origin, lo, hi, lam, pshape=None) -> np.ndarray:
        """Deconvolve img[y0:y1, x0:x1] (unit-scaled with lo/hi) → float32 counts of that box."""
        y0, y1, x0, x1 = box
        hh, ww = y1 - y0, x1 - x0
        plan = self._plan(pshape or self.padded_shape((hh, ww), w.shape))
        rng = hi - lo
        K, K2 = self._otf(plan, w, origin)   # before `prepare`: a cache miss uses plan.rin
        prepare(img, y0, x0, hh, ww, np.float32(lo), np.float32(1.0 / rng), plan.rin)
        kty = plan.spec
        conj_mul(K, plan.fwd(), kty)
        if self.method == "wiener":
            wiener_solve(kty, K2, plan.g2, np.float32(1.0 / lam), plan.norm, plan.cin)
            x = plan.inv()
        else:
            x = self._kf_steps(plan, kty, K2, lam, wstep_div, xstep)
        out = np.empty((hh, ww), np.float32)
        finish(x, hh, ww, np.float32(lo), np.float32(rng), out)
        return out

    def run(self, image: np.ndarray, kernel, *, value_range: tuple[float, float] | None = None) -> np.ndarray:
        """Deconvolve a whole frame with one kernel (the paper's method). Counts in, float32 counts out.

        `value_range` (lo, hi) overrides the robust range used for unit scaling (and so λ's scale).
        """
        img = check_image(image)
        w, origin = check_kernel(kernel)
        if self.split is not None and self.split != (1, 1):
            return self.run_varying(img, _SplitGrid(kernel, img.shape, self.split), overlap=SPLIT_OVERLAP,
                                    uniform_tol_px=0, value_range=value_range)
        lo, hi = value_range_of(img, value_range)
        lam = self.last_lam = self.lam_for(img, lo, hi)
        self.last_cells = 1
        return self._solve(img, (0, img.shape[0], 0, img.shape[1]), w, origin, lo, hi, lam)

    def run_varying(self, image: np.ndarray, grid, *, overlap: float = TILE_OVERLAP,
                    uniform_tol_px: float = 0.5,
                    value_range: tuple[float, float] | None = None,
                    margin_px: int | None = None) -> np.ndarray:
        """Spatially varying deconvolution over a kernel grid (``grid.kernels[r][c]``,
        ``grid.centers[r][c] = (y, x)``): one tile per cell, raised-cosine partition-of-unity blend.

        Each tile is its cell's blending support plus `margin_px` real neighbouring pixels (default
        `TILE_MARGIN_PX`), extended periodically by `self.margin` px to an FFT size shared by all
        tiles of the frame. The tiles are solved in stacks (`TILE_STACK_POINTS`): each K&F step is
        one FFTW call and one numba pass over a stack, not one per tile — the same arithmetic with
        a fraction of the per-call overhead (6×8 tiles: 1.75× a uniform solve instead of 2.0×,
        benchmarks/results/deconv.md). `last_cells` then says how many cells were solved (1 when
        the uniform shortcut below fired), for a caller that books the solve's cost.

        The inverse of a thermal (exponential comet) kernel is local, so the
        tile's boundary effects stay within a few pixels: a margin of the whole kernel size, as
        before, changed no PSNR on the roll-heavy family and cost 20–40 % more. `overlap` is the
        blend ramp as a fraction of the cell spacing (see the module docstring for the measured
        grid × overlap trade-off). When `kernel_spread(grid)` ≤ `uniform_tol_px` (no roll, narrow
        field of view) the frame is solved once with the central kernel (0 disables the shortcut).
        """
        img = check_image(image)
        kernels = getattr(grid, "kernels", None)
        centers = getattr(grid, "centers", None)
        if kernels is None or centers is None:
            raise DeconvError(f"grid: expected an object with .kernels and .centers, "
                              f"got {type(grid).__name__}")
        centers = np.asarray(centers, dtype=np.float64)
        nr = len(kernels)
        nc = len(kernels[0]) if nr else 0
        if nr == 0 or nc == 0 or any(len(row) != nc for row in kernels) or centers.shape != (nr, nc, 2):
            raise DeconvError(f"grid: expected R×C kernels and centers of shape (R, C, 2), got {nr} rows "
                              f"and centers of shape {centers.shape}")
        if not 0 < overlap <= 1:
            raise DeconvError(f"overlap: expected a fraction in (0, 1], got {overlap}")
        m = TILE_MARGIN_PX if margin_px is None else margin_px
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 0:
            raise DeconvError(f"margin_px: expected a non-negative integer, got {margin_px!r}")
        h, wd = img.shape
        lo, hi = value_range_of(img, value_range)
        lam = self.last_lam = self.lam_for(img, lo, hi)   # one λ for every tile: consistent blending
        checked = [check_kernel(kernels[r][c], f"grid.kernels[{r}][{c}]")
                   for r in range(nr) for c in range(nc)]
        weights, origins = stack_kernels(checked)
        r, c = central_cell(centers, (h, wd))
        mid = r * nc + c
        if uniform_tol_px > 0:
            mom = moments(weights, origins)
            if float(np.abs(mom - mom[mid]).max()) <= uniform_tol_px:
                w, origin = checked[mid]
                self.last_cells = 1
                return self._solve(img, (0, h, 0, wd), w, origin, lo, hi, lam)
        lay = self._layout(img.shape, centers, overlap, int(m))
        out = np.zeros((h, wd), np.float32)
        n = nr * nc
        most = max(1, TILE_STACK_POINTS // (lay.pshape[0] * lay.pshape[1]))
        step = -(-n // -(-n // most))   # equal stacks of at most `most` tiles
        for a in range(0, n, step):
            sel = slice(a, a + step)
            x = self._solve_stack(img, lay.boxes[sel], weights[sel], origins[sel], lo, hi, lam, lay.pshape)
            blend_stack(x, lay.boxes[sel], lay.supports[sel], lay.rows[sel], lay.cols[sel], lay.wy, lay.wx,
                        np.float32(lo), np.float32(hi - lo), out)
        self.last_cells = n
        return out

    def _layout(self, shape, centers, overlap, m) -> _TileLayout:
        """The tiles of a grid (cached: a live grid keeps its centres from frame to frame)."""
        key = (shape, centers.tobytes(), centers.shape, float(overlap), m, self.margin)
        lay = self._layouts.get(key)
        if lay is None:
            if len(self._layouts) >= 8:
                self._layouts.pop(next(iter(self._layouts)))
            lay = self._layouts[key] = _TileLayout(shape, centers, overlap, m, self.margin)
        return lay

    def _solve_stack(self, img, boxes, weights, origins, lo, hi, lam, pshape) -> np.ndarray:
        """Deconvolve the tiles img[y0:y1, x0:x1] of `boxes` (n, 4), tile t blurred by weights[t] with
        its origin at origins[t] (a `stack_kernels` stack), all in one stack of FFT size `pshape`:
        the steps of `_solve`, each one FFTW call or numba pass over every tile. Returns the
        unit-range solutions (n, hp, wp) in a plan buffer (overwritten by the next solve)."""
        plan = self._plan((len(boxes), *pshape))
        scatter_psfs(weights, origins, plan.rin)
        otf_stack(plan.fwd(), plan.K, plan.K2)
        rng = hi - lo
        prepare_stack(img, boxes, np.float32(lo), np.float32(1.0 / rng), plan.rin)
        kty = plan.spec
        conj_mul_stack(plan.K, plan.fwd(), kty)
        if self.method == "wiener":
            wiener_stack(kty, plan.K2, plan.g2, np.float32(1.0 / lam), plan.norm, plan.cin)
            return plan.inv()
        return self._kf_steps(plan, kty, plan.K2, lam, wstep_div_stack, xstep_stack)

    def _kf_steps(self, plan: Plan, kty, K2, lam: float, wstep, xstep) -> np.ndarray:
        """K&F's half-quadratic continuation (w-step, then x-step, per β) on a plan's buffers, with the
        numba passes for one frame (`wstep_div`, `xstep`) or a stack of tiles (`*_stack`)."""
        x = plan.rin  # the w-step reads x fully before writing div into the same buffer
        mode = 0 if self.alpha == 1.0 else 1
        inv_step = np.float32((LUT_SIZE - 1) / LUT_VMAX)
        for beta, lut, tau in zip(self._betas, self._luts, self._taus, strict=True):
            wstep(x, mode, np.float32(1.0 / beta), np.float32(tau), lut, inv_step,
                  np.float32(self.alpha), plan.wx, plan.wy, plan.div, plan.idx)
            xstep(kty, K2, plan.g2, plan.fwd(), np.float32(beta / lam), plan.norm, plan.cin)
            x = plan.inv()
        return x


class _TileLayout:
    """Where each cell's tile lies: blending support and partition-of-unity weights
    (`tile_weights`), box = support + `m` real pixels, one FFT size for all (+ `pad` periodic)."""

    def __init__(self, shape, centers, overlap, m, pad):
        h, wd = shape
        nr, nc = centers.shape[:2]
        wys = tile_weights(h, centers[:, :, 0].mean(axis=1), overlap)
        wxs = tile_weights(wd, centers[:, :, 1].mean(axis=0), overlap)
        self.rows, self.cols = (a.ravel().astype(np.int64) for a in np.indices((nr, nc)))
        self.supports = np.array([(wys[r][0], wys[r][1], wxs[c][0], wxs[c][1])
                                  for r, c in zip(self.rows, self.cols, strict=True)], np.int64)
        sp = self.supports
        self.boxes = np.stack([np.maximum(sp[:, 0] - m, 0), np.minimum(sp[:, 1] + m, h),
                               np.maximum(sp[:, 2] - m, 0), np.minimum(sp[:, 3] + m, wd)], axis=1)
        self.pshape = (fast_len(int((self.boxes[:, 1] - self.boxes[:, 0]).max()) + pad),
                       fast_len(int((self.boxes[:, 3] - self.boxes[:, 2]).max()) + pad))
        self.wy = np.zeros((nr, max(len(v[2]) for v in wys)), np.float32)
        self.wx = np.zeros((nc, max(len(v[2]) for v in wxs)), np.float32)
        for r, v in enumerate(wys):
            self.wy[r, :len(v[2])] = v[2]
        for c, v in enumerate(wxs):
            self.wx[c, :len(v[2])] = v[2]


class _SplitGrid:
    """One kernel on an even rows × cols grid (`Deconvolver(split=…)`)."""

    def __init__(self, kernel, shape, split):
        rows, cols = split
        ye = np.linspace(0, shape[0], rows + 1)
        xe = np.linspace(0, shape[1], cols + 1)
        self.kernels = [[kernel] * cols for _ in range(rows)]
        self.centers = np.array([[((ye[i] + ye[i + 1] - 1) / 2, (xe[j] + xe[j + 1] - 1) / 2)
                                  for j in range(cols)] for i in range(rows)])


_DEFAULT: dict = {}
_DEFAULT_LOCK = threading.Lock()


def _shared(method, alpha, lam) -> Deconvolver:
    key = (threading.get_ident(), method, float(alpha), lam)
    with _DEFAULT_LOCK:
        d = _DEFAULT.get(key)
        if d is None:
            d = _DEFAULT[key] = Deconvolver(method=method, alpha=alpha, lam=lam)
    return d


def deconvolve(blurry: np.ndarray, kernel, *, method: str = "kf", alpha: float = DEFAULT_ALPHA,
               lam: float | None = None) -> np.ndarray:
    """Deconvolve one frame with one kernel (Eq. 18 kernel, K&F or Wiener). Counts in → float32 counts.

    Uses a per-thread cached `Deconvolver`; see its docstring for the parameters.
    """
    return _shared(method, alpha, lam).run(blurry, kernel)


def deconvolve_varying(blurry: np.ndarray, grid, *, method: str = "kf", alpha: float = DEFAULT_ALPHA,
                       lam: float | None = None, overlap: float = TILE_OVERLAP,
                       uniform_tol_px: float = 0.5) -> np.ndarray:
    """Spatially varying deconvolution in overlapping tiles, one kernel per grid cell (float32 counts)."""
    dec = _shared(method, alpha, lam)
    return dec.run_varying(blurry, grid, overlap=overlap, uniform_tol_px=uniform_tol_px)
