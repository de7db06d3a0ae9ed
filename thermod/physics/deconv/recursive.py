"""Recursive temporal deconvolution: the previous restored frame, warped by the gyro into frame t's
geometry, is the prior of frame t's solve (a Kalman filter per spatial frequency).

Frame t is solved alone by Wiener (x₀) and corrected, per frequency, to the posterior mean
(K̄Y + (A + αR) T² P) / D, D = |K|² + αR + A T², with K̄Y = (|K|² + R) X₀:

    X = X₀ + w (P − X₀) + v X₀,   w = (A + αR) T² / D,   v = (R − αR (1 − T²)) / D

R = |F∇|²/λ is the single-frame solve's Tikhonov prior, α = `PRIOR_WEIGHT` its weight in the
combination, A the prior's data information (forgotten by γ = `MEMORY` per frame and limited by a
registration error of `REGISTRATION_PX`), T the warp's interpolation gain (`interpolation_gain`).
v X₀ undoes x₀'s shrinkage; it is applied to x₀ before the prior's mask, so no mask edge rings.

The rule it keeps: where the warped prior disagrees with x₀ beyond x₀'s own predicted noise (a
moving hot object, parallax, new scene at a border, an FFC step, a registration error) or the gyro
does not reach it, it is replaced by x₀ (``p' = m p + (1 − m) x₀``), so there the solve returns x₀
exactly; an FFC offset (the median of x₀ − p) is removed first. `half_test` runs that test on 2×2
means. The derivation, the information update and the cost per frame (`last_fft_pairs`):
docs/design.md §1.5, "Temporal deconvolution, the recursive solve".
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft
from numba import njit

from .checks import DeconvError, check_frame, check_kernel
from .noise import noise_sigma, value_range_of
from .plans import fast_len, gradient_power, place_kernel
from .solver import TILE_OVERLAP, Deconvolver
from .temporal import MAP_STEP_PX, coarse_warp_maps
from .tiles import TILE_MARGIN_PX
from .xstep import prepare

MEMORY = 0.8                 # γ: carried information kept per frame (memory ~ 1 / (1 − γ) = 5 frames)
REGISTRATION_PX = 0.1        # δ: registration + interpolation error of a warped prior (px RMS)
WINDOW_PX = 9                # box of the local mean square of the disagreement test
TEST_WINDOW_PX = 5           # box (on the 2×2 means: ~10 px) of the disagreement test's local mean square
DISAGREE = (2.0, 4.0)        # test's local mean square / its reference: full weight below, none above
HALF_TEST_SLACK = 4.0        # the test on 2×2 means: its reference × this (the means cut x₀'s noise by
                             # up to 4, not a misregistration's residual at the blur's scale)
PRIOR_WEIGHT = 2.0           # α: the image prior's weight in the combination (1: −0.40 dB on multirotor:40)
MAX_AGE_S = 0.1              # a prior older than this (camera clock) is not used
SUPPORT_INSET_PX = 4         # warped support shrunk by this much (interpolation, the cubic's reach)
SPECTRUM_MIN = 128           # the weights' spectrum: at least this many points per axis (a power of two)
SPECTRUM_OVERSAMPLE = 4      # ... and at least this many per kernel length, so |K|² is sampled finely

PROFILE: dict[str, float] = {}   # thread CPU seconds per stage of the last correction (for profiling)


def _lap(stage: str, t: float) -> float:
    now = time.thread_time()
    PROFILE[stage] = PROFILE.get(stage, 0.0) + now - t
    return now


@dataclass(frozen=True)
class Estimate:
    """One restored frame as the next frame's prior: the output (float32 counts), its read time
    (camera clock, last row) and its data information I(f) on the half spectrum of `shape`."""

    image: np.ndarray
    t_frame: float
    info: np.ndarray
    shape: tuple[int, int]


# ---------------------------------------------------------------------------------- numba passes
@njit(cache=True, nogil=True, fastmath=True)
def _spectral_weights(info, rows, cols, gain, q, K2, T2, g2, c, alpha, norm, by, bx, H, W, V, I):
    """One pass over the half spectrum. With A = gain · Iₒ / (1 + q Iₒ) (the carried information,
    Iₒ the prior's at the nearest old frequency), R = c |F∇|², D = |K|² + αR + A T²:
    H = norm |K|² / (|K|² + R) (the single solve's response), W = norm (A + αR) T² / D and
    V = norm (R − αR (1 − T²)) / D (the correction's), I = |K|² + A T² (this frame's information).
    Returns the mean over the full spectrum of |K|² / (|K|² + R)² (the Wiener solution's white-noise
    gain, Parseval) and the same times by[i]·bx[j] (its gain after a filter of that power response,
    e.g. a 2×2 mean)."""
    h, w = K2.shape
    one, zero, eps = np.float32(1.0), np.float32(0.0), np.float32(1e-12)
    gain, q, c = np.float32(gain), np.float32(q), np.float32(c)
    alpha, norm = np.float32(alpha), np.float32(norm)
    full_w = 2 * (w - 1)
    mult = np.empty(w, np.float32)         # columns the half spectrum stands for (1 or 2)
    mult_b = np.empty(w, np.float32)
    for j in range(w):
        mult[j] = 1.0 if (j == 0 or (j == w - 1 and full_w % 2 == 0)) else 2.0
        mult_b[j] = mult[j] * bx[j]
    acc = 0.0
    acc_b = 0.0
    for i in range(h):
        # row views and float32 row sums let the inner loop vectorise (2.2× faster than indexing)
        inf, k2i, g2i, t2i = info[rows[i]], K2[i], g2[i], T2[i]
        Hi, Wi, Vi, Ii = H[i], W[i], V[i], I[i]
        s = np.float32(0.0)
        s_b = np.float32(0.0)
        for j in range(w):
            v = inf[cols[j]]
            a = gain * v / (one + q * v)
            a = a if v > 0 else zero
            k2 = k2i[j]
            r = c * g2i[j]
            t2 = t2i[j]
            inv = one / (k2 + r + eps)
            Hi[j] = norm * k2 * inv
            ar = alpha * r
            d = norm / (k2 + ar + a * t2 + eps)
            Wi[j] = (a + ar) * t2 * d
            Vi[j] = (r - ar * (one - t2)) * d
            Ii[j] = k2 + a * t2
            g = k2 * inv * inv
            s += mult[j] * g
            s_b += mult_b[j] * g
        acc += s
        acc_b += s_b * by[i]
    n = h * float(mult.sum())
    return acc / n, acc_b / n


@njit(cache=True, nogil=True)
def _mean_square_step(p, step):
    """½ (mean of the squared differences along y + along x) of p's every `step`-th row and column."""
    h, w = (p.shape[0] + step - 1) // step, (p.shape[1] + step - 1) // step
    sy = 0.0
    sx = 0.0
    for i in range(h):
        for j in range(w):
            v = p[i * step, j * step]
            if i + 1 < h:
                d = p[(i + 1) * step, j * step] - v
                sy += d * d
            if j + 1 < w:
                d = p[i * step, (j + 1) * step] - v
                sx += d * d
    return 0.5 * (sy / max((h - 1) * w, 1) + sx / max(h * (w - 1), 1))


_INTERP_REACH = {cv2.INTER_LINEAR: 1, cv2.INTER_CUBIC: 2, cv2.INTER_LANCZOS4: 4}


def _interp_weights(x: np.ndarray, interpolation: int) -> np.ndarray:
    """cv2's interpolation kernel at offsets x (linear, cubic with a = −0.75, Lanczos-4)."""
    a = np.abs(x)
    if interpolation == cv2.INTER_LINEAR:
        return np.clip(1 - a, 0, None)
    if interpolation == cv2.INTER_CUBIC:
        c = -0.75
        return np.where(a <= 1, (c + 2) * a ** 3 - (c + 3) * a ** 2 + 1,
                        np.where(a < 2, c * a ** 3 - 5 * c * a ** 2 + 8 * c * a - 4 * c, 0.0))
    return np.where(a < 4, np.sinc(x) * np.sinc(x / 4), 0.0)


def interpolation_gain(interpolation: int, f: np.ndarray) -> np.ndarray:
    """The mean gain (over sub-pixel positions) of a cv2 interpolation at frequencies f (cycles/px):
    what a warped image keeps of its content there (1-D; the 2-D gain is the product)."""
    reach = _INTERP_REACH[interpolation]
    k = np.arange(-reach + 1, reach + 1, dtype=np.float64)
    acc = np.zeros(len(f))
    shifts = (np.arange(32) + 0.5) / 32
    for s in shifts:
        w = _interp_weights(k - s, interpolation)
        w /= w.sum()
        acc += np.real(np.exp(2j * np.pi * np.outer(f, k - s)) @ w)
    return np.clip(acc / len(shifts), 0.0, 1.0)


@njit(cache=True, nogil=True)
def _squared_misfit(x0, pred, lo, scale, out):
    """out = ((x0 − lo)·scale − pred)² over x0's shape (pred: the padded unit-range prediction)."""
    h, w = x0.shape
    for i in range(h):
        for j in range(w):
            d = (x0[i, j] - lo) * scale - pred[i, j]
            out[i, j] = d * d


@njit(cache=True, nogil=True)
def _agreement(e, support, full, none, out):
    """out = support · clip((none − e) / (none − full), 0, 1): 1 below `full`, 0 above `none`."""
    h, w = e.shape
    inv = 1.0 / (none - full)
    for i in range(h):
        for j in range(w):
            v = (none - e[i, j]) * inv
            out[i, j] = support[i, j] * (0.0 if v < 0 else (1.0 if v > 1 else v))


@njit(cache=True, nogil=True)
def _add_correction(x0, corr, rng, out):
    h, w = x0.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = x0[i, j] + corr[i, j] * rng


@njit(cache=True, nogil=True)
def _fill_mirrored(x0, lo, scale, out):
    """out = x₀ (unit range), mirrored beyond its edges (cv2's BORDER_REFLECT): a step at the frame's
    edge would ring through v."""
    hp, wp = out.shape
    h, w = x0.shape
    for i in range(hp):
        si = i if i < h else max(2 * h - 1 - i, 0)
        for j in range(wp):
            sj = j if j < w else max(2 * w - 1 - j, 0)
            out[i, j] = (x0[si, sj] - lo) * scale


@njit(cache=True, nogil=True)
def _add_masked(out, m, u, rng):
    """out += m · u · rng over out's shape (u: padded)."""
    h, w = out.shape
    for i in range(h):
        for j in range(w):
            out[i, j] += m[i, j] * u[i, j] * rng


@njit(cache=True, nogil=True)
def _fill_difference(p, x0, m, lo, scale, out):
    """out[:h, :w] = m · (p − x0) (unit range), zero beyond: outside the frame x₀ is trusted."""
    hp, wp = out.shape
    h, w = p.shape
    for i in range(hp):
        for j in range(wp):
            if i < h and j < w:
                out[i, j] = m[i, j] * (p[i, j] - x0[i, j]) * scale
            else:
                out[i, j] = 0.0


@njit(cache=True, nogil=True)
def _upsample_maps(cx, cy, step, inset, mx, my, support):
    """mx, my [H, W]: the coarse maps (node (r, c) at pixel (r·step, c·step)) interpolated bilinearly;
    support = 1 where the map lands at least `inset` px inside the [H, W] source frame, else 0."""
    H, W = mx.shape
    nr, nc = cx.shape
    rx = np.empty((nr, W), np.float32)       # every coarse row interpolated along x first
    ry = np.empty((nr, W), np.float32)
    for j in range(W):
        fx = j / step
        c = min(int(fx), nc - 2)
        ax = fx - c
        for r in range(nr):
            rx[r, j] = (1 - ax) * cx[r, c] + ax * cx[r, c + 1]
            ry[r, j] = (1 - ax) * cy[r, c] + ax * cy[r, c + 1]
    xlo, xhi, ylo, yhi = inset, W - 1 - inset, inset, H - 1 - inset
    for i in range(H):
        fy = i / step
        r = min(int(fy), nr - 2)
        ay = np.float32(fy - r)
        by = np.float32(1.0) - ay
        for j in range(W):
            x = by * rx[r, j] + ay * rx[r + 1, j]
            y = by * ry[r, j] + ay * ry[r + 1, j]
            mx[i, j] = x
            my[i, j] = y
            support[i, j] = np.float32((x >= xlo) & (x <= xhi) & (y >= ylo) & (y <= yhi))


@njit(cache=True, nogil=True)
def _weigh_sampled(wgt, rows, cols, factor, X, out):
    """out = factor · wgt[rows[i], cols[j]] · X (a weight read off another spectrum's grid)."""
    h, w = X.shape
    for i in range(h):
        ri = rows[i]
        for j in range(w):
            out[i, j] = X[i, j] * (factor * wgt[ri, cols[j]])


def _spectrum_shape(kshape, plan_shape) -> tuple[int, int]:
    """The grid the spectral weights are computed on: a power of two per axis, at least `SPECTRUM_MIN`
    and `SPECTRUM_OVERSAMPLE` kernel lengths, at most the frame's FFT size. |K|² varies over
    1 / (kernel length), the prior's gain and the image prior more slowly, so the weights are read
    off this grid at each of the frame's frequencies (nearest) for a fraction of a frame-sized pass."""
    def side(k, n):
        m = SPECTRUM_MIN
        while m < SPECTRUM_OVERSAMPLE * k:
            m *= 2
        return min(m, n)
    return side(kshape[0], plan_shape[0]), side(kshape[1], plan_shape[1])


def _full_shape(half_spectrum: np.ndarray) -> tuple[int, int]:
    """The (even-width) real grid whose half spectrum this is."""
    return half_spectrum.shape[0], 2 * (half_spectrum.shape[1] - 1)


def _weigh_forward(plan, wgt: np.ndarray) -> None:
    """plan.cin = wgt · F(plan.rin), the weights read off their own grid at the plan's frequencies."""
    spec = _full_shape(wgt)
    _weigh_sampled(wgt, _frequency_index(plan.shape[0], spec[0], half=False),
                   _frequency_index(plan.shape[1], spec[1], half=True), np.float32(1.0), plan.fwd(), plan.cin)


@functools.lru_cache(maxsize=64)
def _half_frequency_index(n_half: int, n_full: int, half: bool) -> np.ndarray:
    """Indices into an `n_full`-point spectrum (cycles/px) of an `n_half`-point one's frequencies on a
    grid of twice the pixel pitch (cycles per 2 px). Cached: a frame's shapes repeat (read-only)."""
    f = 0.5 * (np.fft.rfftfreq(n_half) if half else np.fft.fftfreq(n_half))
    idx = np.rint(f * n_full).astype(np.int64)
    return _frozen(np.clip(idx, 0, n_full // 2) if half else idx % n_full)


@functools.lru_cache(maxsize=64)
def _frequency_index(n_new: int, n_old: int, half: bool) -> np.ndarray:
    """Indices into an `n_old`-point spectrum of the frequencies nearest an `n_new`-point one's.
    Cached: a frame's shapes repeat (read-only)."""
    f = np.fft.rfftfreq(n_new) if half else np.fft.fftfreq(n_new)
    idx = np.rint(f * n_old).astype(np.int64)
    return _frozen(np.clip(idx, 0, n_old // 2) if half else idx % n_old)


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


# ---------------------------------------------------------------------------------- the solver
class RecursiveDeconvolver:
    """Frame t restored with the gyro-warped previous estimate as its prior (see the module docstring).

    `solve(frame, kernel, t_frame, gyro_t, gyro_rate, prior)` → (output, Estimate). `prior` is the
    previous frame's `Estimate`, None, or a zero-argument callable returning one (or None): it is
    called once frame t's own solve is done, so a caller whose previous frame is still being solved
    on another thread can wait for it there. Nothing is stored between calls (thread-safe core; one
    instance per thread, as its `single` Deconvolver).

    Parameters
    ----------
    calib : the Calibration (intrinsics, readout, gyro → camera) of the frames and kernels.
    single : the `Deconvolver` of frame t's own solve x₀ (default: Wiener), whose plans, OTF cache
        and λ rule the correction shares.
    memory, registration_px : γ and δ of the information carried (module docstring).
    max_age_s : a prior read longer than this before frame t is not used.
    min_coverage : a kernel whose gyro coverage is below this is solved alone.
    interpolation : cv2 interpolation of the warp.
    overlap, uniform_tol_px : as `Deconvolver.run_varying` (a kernel grid).
    half_test : run the disagreement test on 2×2 means (a quarter of its points; module docstring);
        False: at full size.
    """

    def __init__(self, calib, single: Deconvolver | None = None, *, memory: float = MEMORY,
                 registration_px: float = REGISTRATION_PX, max_age_s: float = MAX_AGE_S,
                 min_coverage: float = 0.99, interpolation: int = cv2.INTER_CUBIC,
                 overlap: float = TILE_OVERLAP, uniform_tol_px: float = 0.5, half_test: bool = True):
        if single is not None and not isinstance(single, Deconvolver):
            raise DeconvError(f"single: expected a Deconvolver, got {type(single).__name__}")
        memory, registration_px, max_age_s = float(memory), float(registration_px), float(max_age_s)
        if not 0 < memory <= 1:
            raise DeconvError(f"memory: expected a share in (0, 1], got {memory}")
        if not (registration_px >= 0 and math.isfinite(registration_px)):
            raise DeconvError(f"registration_px: expected a non-negative error (px), got {registration_px}")
        if not max_age_s > 0:
            raise DeconvError(f"max_age_s: expected a positive age (s), got {max_age_s}")
        if interpolation not in _INTERP_REACH:
            raise DeconvError("interpolation: expected cv2.INTER_LINEAR, INTER_CUBIC or INTER_LANCZOS4, "
                              f"got {interpolation!r}")
        self._gains: dict[tuple[int, int], np.ndarray] = {}
        self._grads: dict[tuple[int, int], np.ndarray] = {}
        self._boxes: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._buf: dict[str, np.ndarray] = {}
        self._buf_shape: tuple[int, int] | None = None
        self.calib = calib
        self.single = single or Deconvolver(method="wiener")
        self.memory, self.registration_px, self.max_age_s = memory, registration_px, max_age_s
        self.min_coverage = float(min_coverage)
        self.half_test = bool(half_test)
        self.interpolation = interpolation
        self.overlap, self.uniform_tol_px = float(overlap), float(uniform_tol_px)
        # what the last `solve` did, for the caller's books
        self.last_prior_frames = 0      # frame periods between the prior and frame t (0: none used)
        self.last_weight = 0.0          # mean prior weight m over the frame (0: solved alone)
        self.last_fft_pairs_single = 0.0
        self.last_fft_pairs = 0.0
        self.last_single: np.ndarray | None = None
        self.last_seconds = (0.0, 0.0)       # (single solve, recursive part) wall time
        self.last_cpu_seconds = (0.0, 0.0)   # the same in thread CPU time

    def solve(self, frame: np.ndarray, kernel, t_frame: float, gyro_t, gyro_rate, prior=None, *,
              value_range: tuple[float, float] | None = None) -> tuple[np.ndarray, Estimate]:
        """Restore `frame` (counts, calibration-sized) read at `t_frame` (camera clock, last row) with
        its `kernel` (Kernel or KernelGrid) and the `prior` (see the class docstring). Returns the
        float32 counts and this frame's `Estimate` (the next frame's prior).

        `gyro_t`, `gyro_rate`: raw gyro samples spanning the prior's and this frame's read times
        (a ring buffer may be passed whole); without them the frame is solved alone."""
        img, t_frame = check_frame(frame, self.calib, t_frame)
        t0, c0 = time.perf_counter(), time.thread_time()
        lo, hi = value_range_of(img, value_range)
        dec = self.single
        grid = hasattr(kernel, "kernels")
        if grid:
            x0 = dec.run_varying(img, kernel, overlap=self.overlap, uniform_tol_px=self.uniform_tol_px,
                                 value_range=(lo, hi))
        else:
            x0 = dec.run(img, kernel, value_range=(lo, hi))
        x0 = np.asarray(x0, np.float32)
        lam, cells = dec.last_lam, dec.last_cells
        self.last_single = x0
        t1, c1 = time.perf_counter(), time.thread_time()
        k0 = kernel.kernel_at((img.shape[0] - 1) / 2, (img.shape[1] - 1) / 2) if grid else kernel
        w, origin = check_kernel(k0)
        shape = tuple(dec.padded_shape(img.shape, w.shape))
        plan = dec._plan(shape)
        spec = _spectrum_shape(w.shape, shape)
        K2 = self._kernel_power(w, origin, spec)
        self._count_single(img.shape, kernel, cells if grid else 1, shape, dec)
        c = np.float32(1.0 / lam)
        out, info = x0, None
        self.last_prior_frames, self.last_weight = 0, 0.0
        past = prior() if callable(prior) else prior
        if past is not None and getattr(kernel, "coverage", 1.0) >= self.min_coverage:
            got = self._correct(img, x0, past, t_frame, gyro_t, gyro_rate, lo, hi, plan, K2, c)
            if got is not None:
                out, info = got
        if info is None:
            info = K2.copy()
        self.last_seconds = (t1 - t0, time.perf_counter() - t1)
        self.last_cpu_seconds = (c1 - c0, time.thread_time() - c1)
        return out, Estimate(out, t_frame, info, spec)

    def _count_single(self, img_shape, kernel, cells, shape, dec) -> None:
        steps = len(dec._betas) if dec.method == "kf" else 0
        pairs = float(steps + 1)
        if cells > 1:
            lay = dec._layout(img_shape, np.asarray(kernel.centers, np.float64), self.overlap, TILE_MARGIN_PX)
            pairs *= cells * lay.pshape[0] * lay.pshape[1] / (shape[0] * shape[1])
        self.last_fft_pairs_single = self.last_fft_pairs = pairs

    def _correct(self, img, x0, past: Estimate, t_frame, gyro_t, gyro_rate, lo, hi, plan, K2, c):
        """(x, I) with the prior `past` entered, or None when it cannot be (too old, no gyro, no overlap)."""
        age = t_frame - float(past.t_frame)
        if not 0 < age <= self.max_age_s or past.image.shape != img.shape:
            return None
        tp = time.thread_time()
        coarse = coarse_warp_maps(self.calib, gyro_t, gyro_rate, t_frame, float(past.t_frame))
        if coarse is None:
            return None
        tp = _lap("maps", tp)
        H, W = img.shape
        buf = self._buffers(img.shape)
        mx, my, support, p = buf["mx"], buf["my"], buf["support"], buf["p"]
        _upsample_maps(coarse[0], coarse[1], float(MAP_STEP_PX), float(SUPPORT_INSET_PX), mx, my, support)
        ok = support[::4, ::4] > 0
        if ok.mean() < 0.02:
            return None
        tp = _lap("support", tp)
        cv2.remap(past.image, mx, my, self.interpolation, dst=p, borderMode=cv2.BORDER_REPLICATE)
        tp = _lap("warp", tp)
        n = max(1, int(round(age * float(self.calib.frame_rate_hz))))
        scale = np.float32(1.0 / (hi - lo))
        # an FFC step (or drift) offsets the new frame's counts: the prior follows
        p += np.float32(np.median((x0[::8, ::8] - p[::8, ::8])[ok[::2, ::2]]))
        tp = _lap("offset", tp)
        sigma = self.single.last_sigma      # frame t's own solve measured it (NaN: a fixed λ)
        sigma = max(sigma if math.isfinite(sigma) else noise_sigma(img, (lo, hi)), 1e-6)
        tp = _lap("noise", tp)
        grad2 = _mean_square_step(p, 2) * float(scale) ** 2 / 4.0
        q = self.registration_px ** 2 * grad2 / sigma ** 2
        tp = _lap("grad", tp)
        spec = _full_shape(K2)
        rows = _frequency_index(spec[0], past.shape[0], half=False)
        cols = _frequency_index(spec[1], past.shape[1], half=True)
        Hw, Ww, Vw, info = (np.empty_like(K2) for _ in range(4))
        by, bx = self._box_gain(spec)
        nb_full, nb_half = _spectral_weights(past.info, rows, cols, self.memory ** n, n * q, K2,
                                             self._gain(spec), self._g2(spec), float(c), PRIOR_WEIGHT,
                                             float(plan.norm), by, bx, Hw, Ww, Vw, info)
        tp = _lap("spectral_w", tp)
        if self.half_test:
            m = self._test_half(img, x0, p, support, ok, buf, plan, Hw, lo, scale, sigma * sigma * nb_half)
        else:
            m = self._test_full(img, x0, p, support, ok, buf, plan, Hw, lo, scale, sigma * sigma * nb_full)
        tp = _lap("test", tp)
        self.last_weight = float(m[::4, ::4].mean())
        self.last_prior_frames = n
        tp = _lap("mean", tp)
        # the correction x₀ + F⁻¹[w F(m (p − x₀))] + m F⁻¹[v F(x₀)]
        _fill_difference(p, x0, m, np.float32(lo), scale, plan.rin)
        tp = _lap("corr_fill", tp)
        _weigh_forward(plan, Ww)
        tp = _lap("corr_fwd", tp)
        out = np.empty_like(x0)
        _add_correction(x0, plan.inv(), np.float32(hi - lo), out)
        tp = _lap("corr_inv", tp)
        _fill_mirrored(x0, np.float32(lo), scale, plan.rin)
        _weigh_forward(plan, Vw)
        _add_masked(out, m, plan.inv(), np.float32(hi - lo))
        tp = _lap("unshrink", tp)
        # the test's pair (a quarter of the points with half_test), the correction's and the unshrinking's
        self.last_fft_pairs += 3.0 - (0.75 if self.half_test else 0.0)
        return out, info

    def _test_full(self, img, x0, p, support, ok, buf, plan, Hw, lo, scale, expected):
        """The prior's weight m: x₀ against the single solve's output for data k ⊛ p."""
        H, W = img.shape
        prepare(p, 0, 0, H, W, np.float32(lo), scale, plan.rin)
        _weigh_forward(plan, Hw)
        r2 = buf["r2"]
        _squared_misfit(x0, plan.inv(), np.float32(lo), scale, r2)
        e = cv2.blur(r2, (WINDOW_PX, WINDOW_PX))
        inside = e[::4, ::4][ok]
        ref = max(expected, float(np.median(inside)) if inside.size else expected)
        dlo, dhi = DISAGREE
        _agreement(e, support, np.float32(dlo * ref), np.float32(dhi * ref), r2)
        return cv2.blur(r2, (5, 5))             # soft edges: no seam where the prior starts

    def _test_half(self, img, x0, p, support, ok, buf, plan, Hw, lo, scale, expected):
        """The same test on 2×2 means (a quarter of the points), its weight up-sampled."""
        H, W = img.shape
        h2, w2 = H // 2, W // 2
        x0h, ph, r2h = buf["x0h"], buf["ph"], buf["r2h"]
        cv2.resize(x0, (w2, h2), dst=x0h, interpolation=cv2.INTER_AREA)
        cv2.resize(p, (w2, h2), dst=ph, interpolation=cv2.INTER_AREA)
        hplan = self.single._plan(tuple(fast_len((v + 1) // 2) for v in plan.shape))
        prepare(ph, 0, 0, h2, w2, np.float32(lo), scale, hplan.rin)
        hrows = _half_frequency_index(hplan.shape[0], Hw.shape[0], half=False)
        hcols = _half_frequency_index(hplan.shape[1], _full_shape(Hw)[1], half=True)
        _weigh_sampled(Hw, hrows, hcols, np.float32(hplan.norm / plan.norm), hplan.fwd(), hplan.cin)
        _squared_misfit(x0h, hplan.inv(), np.float32(lo), scale, r2h)
        e = cv2.blur(r2h, (TEST_WINDOW_PX, TEST_WINDOW_PX))
        inside = e[::4, ::4][ok[::2, ::2][:(h2 + 3) // 4, :(w2 + 3) // 4]]
        ref = HALF_TEST_SLACK * max(expected, float(np.median(inside)) if inside.size else expected)
        dlo, dhi = DISAGREE
        _agreement(e, support[:2 * h2:2, :2 * w2:2], np.float32(dlo * ref), np.float32(dhi * ref), r2h)
        mh = cv2.blur(r2h, (3, 3))
        return cv2.resize(mh, (W, H), dst=buf["m"], interpolation=cv2.INTER_LINEAR)

    def _buffers(self, shape) -> dict[str, np.ndarray]:
        """Work arrays of a frame shape (reused: one instance per thread)."""
        if self._buf_shape != shape:
            H, W = shape
            f = lambda h, w: np.empty((h, w), np.float32)  # noqa: E731
            self._buf = dict(mx=f(H, W), my=f(H, W), support=f(H, W), p=f(H, W), m=f(H, W), r2=f(H, W),
                             x0h=f(H // 2, W // 2), ph=f(H // 2, W // 2), r2h=f(H // 2, W // 2))
            self._buf_shape = shape
        return self._buf

    def _box_gain(self, shape) -> tuple[np.ndarray, np.ndarray]:
        """Power response per axis of a 2×2 mean, cos²(πf), on the half spectrum of `shape`."""
        g = self._boxes.get(shape)
        if g is None:
            g = self._boxes[shape] = (np.cos(np.pi * np.fft.fftfreq(shape[0])) ** 2,
                                      np.cos(np.pi * np.fft.rfftfreq(shape[1])) ** 2)
        return g

    def _kernel_power(self, w: np.ndarray, origin, spec) -> np.ndarray:
        """|K|² of a kernel (origin at index (0, 0)) on the half spectrum of `spec`."""
        K = scipy.fft.rfft2(place_kernel(np.empty(spec, np.float32), w, origin), workers=1)
        return K.real * K.real + K.imag * K.imag       # float32: scipy.fft keeps the input's precision

    def _g2(self, shape) -> np.ndarray:
        """`gradient_power` of `shape`, as the single solve's plans hold it (cached per shape)."""
        g = self._grads.get(shape)
        if g is None:
            g = self._grads[shape] = gradient_power(shape)
        return g

    def _gain(self, shape) -> np.ndarray:
        """|T(f)|² of the warp's interpolation on the half spectrum of `shape` (cached per shape)."""
        g = self._gains.get(shape)
        if g is None:
            ty = interpolation_gain(self.interpolation, np.abs(np.fft.fftfreq(shape[0])))
            tx = interpolation_gain(self.interpolation, np.fft.rfftfreq(shape[1]))
            g = self._gains[shape] = np.square(np.outer(ty, tx)).astype(np.float32)
        return g


__all__ = ["DISAGREE", "MEMORY", "REGISTRATION_PX", "Estimate", "RecursiveDeconvolver"]
