"""Non-blind deconvolution of thermal frames: Krishnan & Fergus hyper-Laplacian, Wiener, tiles.

Forward model (DESIGN.md §1, Eq. 11/18): ``B(p) = Σ_u k(u) S(p − u)`` with the kernel given as
``weights[oy + u_y, ox + u_x]`` and ``origin = (oy, ox)`` the index of zero displacement (not the
array centre: comet-tail kernels are one-sided). Any object with ``weights`` and ``origin``
works (duck-typed ``thermod.physics.kernels.Kernel``).

Krishnan & Fergus 2009, "Fast image deconvolution using hyper-Laplacian priors" (K&F)::

    min_x  (λ/2) ||k ⊛ x − y||²  +  Σ_j |∇_j x|^α                       (K&F Eq. 1)

by half-quadratic splitting: auxiliary ``w ≈ ∇x`` with penalty ``(β/2)||w − ∇x||²``, β from 1 to
256 by ×2√2 (six steps, one inner iteration each, as in their code).

- w-step: per pixel ``min_w |w|^α + (β/2)(w − v)²``. α = 1: soft threshold at 1/β. α = 2/3: the
  analytic root of K&F's quartic ``w⁴ − 3vw³ + 3v²w² − v³w + 8/(27β³) = 0`` (Ferrari), tabulated
  once per β into a lookup table that a fused numba pass interpolates — only for the few
  gradients above the threshold τ(β) (below it w = 0). Other α in (0, 1) are tabulated by
  Newton's method.
- x-step: closed form in the Fourier domain,
  ``X = (K̄·Y + (β/λ) F(∇ᵀw)) / (|K|² + (β/λ)(|F∂x|² + |F∂y|²))``.

**λ convention (K&F's):** λ weights the *data* term for an image scaled to a unit range; the
paper's "λ = 0.001–0.003" prior weight is 1/λ here. Raw counts are mapped to that range by the
frame's robust range (0.5–99.5 percentiles → 0–1, `robust_range`); results come back in the
input's counts, float32, never clipped.

Wiener fast path: one Tikhonov solve with a gradient prior, ``X = K̄Y / (|K|² + (1/λ)|F∇|²)``.

Boundaries: the unit-scaled frame is extended to an FFT-friendly size by a replicate-then-taper
periodic extension (each padded row/column blends the near edge into the opposite edge with a
raised cosine, zero slope at both joins), so circular convolution sees no jump and no ringing
frame appears at the borders. Padding is at least the kernel size per axis, so any kernel size
(100+ px) works.

FFTs: pyFFTW (float32 plans, FFTW_MEASURE, cached per shape) when importable, else scipy.fft
(`workers=`). Measured (benchmarks/bench_deconv.py, 640×480 with a 65 px kernel, one core) the
whole K&F solve takes 13 ms with FFTW and 17 ms with scipy.fft — FFTW's float32 r2c/c2r pair is
~25 % faster — with identical results, so FFTW is the default.

Spatially varying blur (`deconvolve_varying`): each cell of a kernel grid is deconvolved in its
own tile (the cell's blending support plus a margin of real neighbouring pixels), and tiles are
blended with separable raised-cosine weights that form a partition of unity, so there are no
seams. A grid whose kernels all match the central one (centroid and spread within 0.5 px: pure
pan/tilt with a narrow field of view) is solved once, as a uniform blur.

Padded sizes come from a coarse ladder (16 × 5-smooth), so FFT plans are reused across frames
whose kernels differ by a few pixels; the first frame of a new size pays FFTW's planning (~1.5 s
at 640×480) once per machine: the wisdom is kept in `wisdom_path()`.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np
import scipy.fft
from numba import njit

from thermod.errors import ThermodError

try:  # optional (the "test" extra): faster float32 plans
    import pyfftw
except ImportError:  # pragma: no cover - depends on the installation
    pyfftw = None

log = logging.getLogger(__name__)

BETA_START = 1.0
BETA_MAX = 256.0
BETA_RATE = 2.0 * math.sqrt(2.0)
# lam=None: λ = NOISE_LAMBDA[method] / (σ̂ (1 + σ̂/NOISE_KNEE)), σ̂ the frame's noise in unit range
# (`noise_sigma`), clamped to LAMBDA_RANGE: ∝ 1/σ̂ for quiet frames, ∝ 1/σ̂² (the MAP weight) for
# noisy ones. Fitted on simulated SBTI recordings of six real scenes at 12.5 and 75 °/s (best K&F
# λ 3000–6000 at σ̂ = 0.005, 50000–100000 at σ̂ = 0.0005, 100+ at σ̂ = 0.05; benchmarks/).
NOISE_LAMBDA = {"kf": 30.0, "wiener": 0.6}
NOISE_KNEE = 0.006
LAMBDA_RANGE = {"kf": (30.0, 300000.0), "wiener": (3.0, 30000.0)}
DEFAULT_ALPHA = 2.0 / 3.0
RANGE_PERCENTILES = (0.5, 99.5)
# FFTW_MEASURE takes ~0.7 s per plan at 640×480; cut short, its plans ran 45 % slower (measured),
# so plan fully once and keep the wisdom on disk ($THERMOD_CACHE_DIR, else ~/.cache/thermod).
PLANNING_TIMELIMIT_S = 3.0
MAX_PLANS = 8                 # padded shapes kept (LRU), each with its buffers
# 4096 float32 entries (16 kB, stays in L1) over |∇x| ≤ 2 of a unit-range frame; beyond: Newton.
_LUT_VMAX = 2.0
_LUT_SIZE = 4096


class DeconvError(ThermodError):
    """Bad arguments to the deconvolver (names the argument and what was expected)."""


def beta_schedule(beta_start: float = BETA_START, beta_max: float = BETA_MAX,
                  rate: float = BETA_RATE) -> list[float]:
    """K&F continuation: β = 1, 2√2, 8, … while β < 256 (six values)."""
    out, b = [], beta_start
    while b < beta_max:
        out.append(b)
        b *= rate
    return out


# --------------------------------------------------------------------------------------- w-step
def shrink_23_analytic(v: np.ndarray, beta: float) -> np.ndarray:
    """Exact minimiser of ``|w|^(2/3) + (β/2)(w − v)²`` (float64), K&F's closed form.

    Roots of ``w⁴ − 3vw³ + 3v²w² − v³w + 8/(27β³) = 0`` by Ferrari's method in complex
    arithmetic; the minimiser is the real root with ``|v|/2 < w·sgn(v) < |v|`` (at the threshold
    the non-zero minimum sits exactly at v/2), else 0.
    """
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros_like(v)
    nz = v != 0
    vc = v[nz].astype(np.complex128)
    m = 8.0 / (27.0 * beta ** 3)
    v2 = vc * vc
    v3 = v2 * vc
    v4 = v3 * vc
    a = -1.125 * v2
    b2 = 0.25 * v3
    q = -0.125 * m * v2
    r1 = -q / 2.0 + np.sqrt(-(m ** 3) / 27.0 + (m * m * v4) / 256.0)
    u = np.exp(np.log(r1) / 3.0)
    y = 2.0 * (-5.0 / 18.0 * a + u + m / (3.0 * u))
    W = np.sqrt(a / 3.0 + y)
    s_plus = np.sqrt(-(a + y + b2 / W))
    s_minus = np.sqrt(-(a + y - b2 / W))
    roots = np.stack([0.75 * vc + 0.5 * (W + s_plus), 0.75 * vc + 0.5 * (W - s_plus),
                      0.75 * vc + 0.5 * (-W + s_minus), 0.75 * vc + 0.5 * (-W - s_minus)])
    sv = np.sign(v[nz])
    av = np.abs(v[nz])
    r = roots.real * sv
    ok = (np.abs(roots.imag) < 1e-6) & (r > av / 2.0) & (r < av)
    best = np.where(ok, r, 0.0).max(axis=0)
    out[nz] = best * sv
    return out


def shrink_threshold(alpha: float, beta: float) -> float:
    """|v| below which ``min_w |w|^α + (β/2)(w − v)²`` is w = 0 (α in (0, 1))."""
    lam = 1.0 / beta
    w_star = (2.0 * lam * (1.0 - alpha)) ** (1.0 / (2.0 - alpha))
    return w_star + lam * alpha * w_star ** (alpha - 1.0)


def shrink_numeric(v: np.ndarray, beta: float, alpha: float) -> np.ndarray:
    """Minimiser of ``|w|^α + (β/2)(w − v)²`` for any α in (0, 1) by Newton's method (float64).

    g(w) = w − |v| + (α/β) w^(α−1) is convex on w > 0 and positive at w = |v|, so Newton from
    |v| descends monotonically onto the largest root, the non-zero local minimum.
    """
    v = np.asarray(v, dtype=np.float64)
    a = np.abs(v)
    tau = shrink_threshold(alpha, beta)
    w = a.copy()
    big = a > tau
    wb = w[big]
    ab = a[big]
    c = alpha / beta
    for _ in range(60):
        g = wb - ab + c * wb ** (alpha - 1.0)
        dg = 1.0 + c * (alpha - 1.0) * wb ** (alpha - 2.0)
        wb = wb - g / dg
    out = np.zeros_like(v)
    out[big] = wb * np.sign(v[big])
    return out


_LUTS: dict[tuple[float, float], np.ndarray] = {}
_LUT_LOCK = threading.Lock()


def _shrink_lut(alpha: float, beta: float) -> np.ndarray:
    """w(|v|) on a uniform grid over [0, _LUT_VMAX] (float32), built once per (α, β)."""
    key = (round(alpha, 12), round(beta, 9))
    with _LUT_LOCK:
        lut = _LUTS.get(key)
        if lut is None:
            v = np.linspace(0.0, _LUT_VMAX, _LUT_SIZE)
            exact23 = abs(alpha - 2.0 / 3.0) < 1e-9
            w = shrink_23_analytic(v, beta) if exact23 else shrink_numeric(v, beta, alpha)
            lut = _LUTS[key] = w.astype(np.float32)
    return lut


@njit(cache=True, nogil=True, fastmath=True)
def _shrink_row(d, out, mode, inv_beta, tau, lut, inv_step, alpha, idx):
    """out = argmin_w |w|^α + (β/2)(w − d)², elementwise over one row.

    mode 0: α = 1, soft threshold at 1/β (branch-free, vectorises). mode 1: everything at or
    below the threshold τ is 0; the few |d| > τ (a few % of a thermal frame's gradients: most
    of it is flat) are gathered by a branch-free compaction into `idx` and looked up in the
    table (linear interpolation) — 4× faster than looking up every pixel — with a scalar Newton
    fix-up for the rare |d| beyond the table (hot spots far outside the unit range).
    """
    n = d.shape[0]
    if mode == 0:
        for j in range(n):
            v = d[j]
            r = max(abs(v) - inv_beta, np.float32(0.0))
            out[j] = r if v >= 0 else -r
        return
    m = 0
    for j in range(n):
        out[j] = np.float32(0.0)
        idx[m] = j
        m += abs(d[j]) > tau
    nmax = np.float32(lut.shape[0] - 1.001)
    c = alpha * inv_beta
    for k in range(m):
        j = idx[k]
        v = d[j]
        a = abs(v)
        f = a * inv_step
        if f < nmax:
            i = np.int32(f)
            fr = f - np.float32(i)
            r = lut[i] + fr * (lut[i + 1] - lut[i])
        else:
            r = a
            for _ in range(4):  # Newton on w − a + (α/β) w^(α−1) = 0 from w = a (monotone)
                g = r - a + c * r ** (alpha - 1)
                r = r - g / (1 + c * (alpha - 1) * r ** (alpha - 2))
        out[j] = r if v >= 0 else -r


@njit(cache=True, nogil=True, fastmath=True)
def _wstep_div(x, mode, inv_beta, tau, lut, inv_step, alpha, wx, wy, div, idx):
    """w = shrink(∇x) (circular forward differences), then div = ∇ᵀw, in one row-by-row pass.

    `wx` [3, W], `wy` [2, W] and `idx` [W] are row scratch; `div` may alias `x` (row i is written after
    rows i and i + 1 were read; row 0, needed last, is saved first).
    """
    h, w = x.shape
    d = wx[1]
    row0 = wx[2]
    for j in range(w):
        row0[j] = x[0, j]
        d[j] = x[0, j] - x[h - 1, j]
    wprev = wy[0]
    wcur = wy[1]
    wxr = wx[0]
    _shrink_row(d, wprev, mode, inv_beta, tau, lut, inv_step, alpha, idx)
    for i in range(h):
        for j in range(w - 1):
            d[j] = x[i, j + 1] - x[i, j]
        d[w - 1] = x[i, 0] - x[i, w - 1]
        _shrink_row(d, wxr, mode, inv_beta, tau, lut, inv_step, alpha, idx)
        if i + 1 < h:
            for j in range(w):
                d[j] = x[i + 1, j] - x[i, j]
        else:
            for j in range(w):
                d[j] = row0[j] - x[i, j]
        _shrink_row(d, wcur, mode, inv_beta, tau, lut, inv_step, alpha, idx)
        div[i, 0] = (wxr[w - 1] - wxr[0]) + (wprev[0] - wcur[0])
        for j in range(1, w):
            div[i, j] = (wxr[j - 1] - wxr[j]) + (wprev[j] - wcur[j])
        wprev, wcur = wcur, wprev


@njit(cache=True, nogil=True, fastmath=True)
def _xstep(kty, k2, g2, d, c, norm, out):
    """out = norm·(K̄Y + c·D) / (|K|² + c·|G|²) on the half spectrum, c = β/λ (norm: FFTW's 1/N)."""
    h, w = kty.shape
    for i in range(h):
        for j in range(w):
            r = norm / (k2[i, j] + c * g2[i, j])   # real denominator: no complex division
            out[i, j] = (kty[i, j] + c * d[i, j]) * r


@njit(cache=True, nogil=True)
def _conj_mul(k, y, out):
    h, w = k.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = k[i, j].conjugate() * y[i, j]


@njit(cache=True, nogil=True)
def _wiener(kty, k2, g2, c, norm, out):
    h, w = kty.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = norm * kty[i, j] / (k2[i, j] + c * g2[i, j])


@njit(cache=True, nogil=True)
def _prepare(img, y0, x0, hh, ww, lo, scale, out):
    """Unit-scale img[y0:y0+hh, x0:x0+ww] into out[:hh, :ww] and fill the rest of `out` with a
    periodic extension: replicate the edge, raised-cosine blend into the opposite edge."""
    hp, wp = out.shape
    for i in range(hh):
        for j in range(ww):
            out[i, j] = (np.float32(img[y0 + i, x0 + j]) - lo) * scale
    gx = wp - ww
    if gx > 0:
        for j in range(gx):
            c = np.float32(0.5 - 0.5 * math.cos(math.pi * (j + 1) / (gx + 1)))
            for i in range(hh):
                out[i, ww + j] = (1 - c) * out[i, ww - 1] + c * out[i, 0]
    gy = hp - hh
    if gy > 0:
        for i in range(gy):
            c = np.float32(0.5 - 0.5 * math.cos(math.pi * (i + 1) / (gy + 1)))
            for j in range(wp):
                out[hh + i, j] = (1 - c) * out[hh - 1, j] + c * out[0, j]


@njit(cache=True, nogil=True)
def _finish(x, hh, ww, lo, rng, out):
    for i in range(hh):
        for j in range(ww):
            out[i, j] = x[i, j] * rng + lo


# ------------------------------------------------------------------------------------ FFT plans
_WISDOM_LOCK = threading.Lock()
_wisdom_loaded = False


def wisdom_path() -> Path:
    d = os.environ.get("THERMOD_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "thermod")
    return Path(d) / "fftw_wisdom_float32"


def _load_wisdom() -> None:
    global _wisdom_loaded
    with _WISDOM_LOCK:
        if _wisdom_loaded:
            return
        _wisdom_loaded = True
        try:
            pyfftw.import_wisdom((b"", wisdom_path().read_bytes(), b""))
        except (OSError, ValueError, TypeError) as e:  # absent or stale: plan from scratch
            log.debug("no FFTW wisdom loaded (%s)", e)


def _save_wisdom() -> None:
    path = wisdom_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}")
        tmp.write_bytes(pyfftw.export_wisdom()[1])
        os.replace(tmp, path)
    except OSError as e:  # read-only home, sandboxed service: plans still work, just not cached
        log.debug("FFTW wisdom not saved to %s (%s)", path, e)


class _Plan:
    """Real FFT pair for one padded shape: write into `.rin`/`.cin`, call `fwd()`/`inv()`.

    Results live in plan-owned buffers (FFTW) and are overwritten by the next call.
    """

    def __init__(self, shape, backend, workers, measure_unseen=True):
        self.shape = shape
        self.estimated = False  # planned with FFTW_ESTIMATE (no wisdom, real-time caller)
        hp, wp = shape
        self.backend = backend
        self.workers = workers
        # FFTW's inverse is unnormalised: the x-step folds 1/N into its output for free
        self.norm = np.float32(1.0 / (hp * wp) if backend == "fftw" else 1.0)
        if backend == "fftw":
            _load_wisdom()
            self.rin = pyfftw.empty_aligned(shape, "float32")
            self.cout = pyfftw.empty_aligned((hp, wp // 2 + 1), "complex64")
            self.cin = pyfftw.empty_aligned((hp, wp // 2 + 1), "complex64")
            self.rout = pyfftw.empty_aligned(shape, "float32")
            t0 = time.perf_counter()
            try:
                # A real-time caller cannot wait ~0.7 s for a measured plan mid-stream (it would hold
                # up the frame queue): take the saved wisdom if it has this size, else estimate.
                flags = ("FFTW_MEASURE",) if measure_unseen else ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
                self._make_fftw(flags, workers)
            except RuntimeError:
                self.estimated = True
                self._make_fftw(("FFTW_ESTIMATE",), workers)
            if not self.estimated and time.perf_counter() - t0 > 0.05:  # planned anew: remember it
                _save_wisdom()
        else:
            self.rin = np.empty(shape, np.float32)
            self.cin = np.empty((hp, wp // 2 + 1), np.complex64)
        # |F∂x|² + |F∂y|² of the circular forward differences
        ky = np.fft.fftfreq(hp).astype(np.float64)[:, None]
        kx = np.fft.rfftfreq(wp).astype(np.float64)[None, :]
        self.g2 = ((2 - 2 * np.cos(2 * np.pi * kx)) + (2 - 2 * np.cos(2 * np.pi * ky))).astype(np.float32)
        self.wx = np.empty((3, wp), np.float32)  # row scratch for the fused w-step
        self.wy = np.empty((2, wp), np.float32)
        self.idx = np.empty(wp, np.int32)
        self.div = self.rin  # the w-step writes its divergence straight into the FFT input
        self.spec = np.empty((hp, wp // 2 + 1), np.complex64)

    def _make_fftw(self, flags, workers) -> None:
        self._f = pyfftw.FFTW(self.rin, self.cout, axes=(0, 1), flags=flags, threads=workers,
                              planning_timelimit=PLANNING_TIMELIMIT_S)
        self._b = pyfftw.FFTW(self.cin, self.rout, axes=(0, 1), direction="FFTW_BACKWARD",
                              flags=(*flags, "FFTW_DESTROY_INPUT"), threads=workers,
                              planning_timelimit=PLANNING_TIMELIMIT_S)

    def fwd(self) -> np.ndarray:
        if self.backend == "fftw":
            self._f.execute()
            return self.cout
        return scipy.fft.rfft2(self.rin, workers=self.workers)

    def inv(self) -> np.ndarray:
        if self.backend == "fftw":
            self._b.execute()
            return self.rout
        return scipy.fft.irfft2(self.cin, s=self.shape, workers=self.workers)


def _fast_len(n: int) -> int:
    """Smallest m ≥ n with m = 16·k, k = 2^a·3^b·5^c. Measured FFTW r2c+c2r pairs at 640×480
    padding: 512×720 1.07 ms, 500×720 1.16, 540×720 1.45, 576×720 1.30, 512×675 2.32 — powers of
    two pay, odd factors cost, so the coarse ladder loses nothing and lets kernels of slightly
    different sizes share one FFT plan."""
    k = max(1, -(-int(n) // 16))
    while True:
        r = k
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        if r == 1:
            return 16 * k
        k += 1


def _check_kernel(kernel, name="kernel"):
    w = getattr(kernel, "weights", None)
    origin = getattr(kernel, "origin", None)
    if w is None or origin is None:
        raise DeconvError(f"{name}: expected an object with .weights and .origin, "
                          f"got {type(kernel).__name__}")
    w = np.asarray(w)
    if w.ndim != 2 or w.size == 0:
        raise DeconvError(f"{name}.weights: expected a non-empty 2-D array, got shape {w.shape}")
    if not np.issubdtype(w.dtype, np.floating) and not np.issubdtype(w.dtype, np.integer):
        raise DeconvError(f"{name}.weights: expected real numbers, got dtype {w.dtype}")
    w = w.astype(np.float32, copy=False)
    if not np.all(np.isfinite(w)):
        raise DeconvError(f"{name}.weights: contains NaN or infinite values")
    s = float(w.sum(dtype=np.float64))
    if not s > 0:
        raise DeconvError(f"{name}.weights: must sum to a positive value (≈1), got {s}")
    try:
        oy, ox = (int(v) for v in origin)
    except (TypeError, ValueError):
        raise DeconvError(f"{name}.origin: expected (oy, ox) integers, got {origin!r}") from None
    if not (0 <= oy < w.shape[0] and 0 <= ox < w.shape[1]):
        raise DeconvError(f"{name}.origin: {(oy, ox)} lies outside the weights of shape {w.shape}")
    if abs(s - 1.0) > 1e-3:
        w = w / np.float32(s)
    return w, (oy, ox)


def _check_image(image):
    a = np.asarray(image)
    if a.ndim != 2 or min(a.shape) < 2:
        raise DeconvError(f"image: expected a 2-D frame of at least 2×2 pixels, got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise DeconvError(f"image: expected numeric counts, got dtype {a.dtype}")
    if np.issubdtype(a.dtype, np.floating):
        if a.dtype != np.float32:
            a = a.astype(np.float32)
        if not np.isfinite(a[::7, ::7]).all() or not np.isfinite(a).all():
            raise DeconvError("image: contains NaN or infinite values")
    elif a.dtype not in (np.uint16, np.int32, np.uint8, np.int16):
        a = a.astype(np.float32)
    return a


def _value_range(img, value_range) -> tuple[float, float]:
    if value_range is None:
        return robust_range(img)
    try:
        lo, hi = (float(v) for v in value_range)
    except (TypeError, ValueError):
        raise DeconvError(f"value_range: expected (lo, hi) counts, got {value_range!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise DeconvError(f"value_range: expected finite lo < hi, got {(lo, hi)}")
    return lo, hi


def robust_range(image: np.ndarray) -> tuple[float, float]:
    """(lo, hi) counts mapped to 0 and 1 internally: the 0.5/99.5 percentiles of a subsample."""
    step = max(1, int(math.sqrt(image.size / 40000)))
    sub = np.asarray(image[::step, ::step], dtype=np.float32)
    lo, hi = np.percentile(sub, RANGE_PERCENTILES)
    lo, hi = float(lo), float(hi)
    if not hi - lo > 1e-6 * max(1.0, abs(lo)):  # flat frame: any scale works, keep counts
        hi = lo + 1.0
    return lo, hi


@njit(cache=True, nogil=True)
def _immerkaer_sum(img, row_step):
    """Σ |img ⊛ [[1,−2,1],[−2,4,−2],[1,−2,1]]| over interior pixels of every `row_step`-th row."""
    h, w = img.shape
    acc = 0.0
    n = 0
    for i in range(1, h - 1, row_step):
        up, mid, dn = img[i - 1], img[i], img[i + 1]
        for j in range(1, w - 1):
            corners = (np.float32(up[j - 1]) + np.float32(up[j + 1])
                       + np.float32(dn[j - 1]) + np.float32(dn[j + 1]))
            edges = np.float32(up[j]) + np.float32(dn[j]) + np.float32(mid[j - 1]) + np.float32(mid[j + 1])
            acc += abs(corners - 2 * edges + 4 * np.float32(mid[j]))
            n += 1
    return acc, n


def noise_sigma(image: np.ndarray, value_range: tuple[float, float] | None = None) -> float:
    """Temporal-noise RMS of a frame in unit range (Immerkær 1996, "Fast noise variance estimation").

    The Laplacian-difference mask cancels smooth structure; blur removes most of the rest, so on a
    blurry frame this is close to the sensor noise (NETD) over the frame's robust range.
    """
    img = _check_image(image)
    lo, hi = robust_range(img) if value_range is None else value_range
    if min(img.shape) < 3:
        return 0.0
    acc, n = _immerkaer_sum(img, max(1, img.shape[0] // 64))   # ~64 rows: plenty of samples
    return float(math.sqrt(math.pi / 2) / 6 * acc / max(n, 1) / (hi - lo))


def _tile_weights(n: int, centers: np.ndarray, overlap: float) -> list[tuple[int, int, np.ndarray]]:
    """Separable raised-cosine partition of unity along one axis of length n.

    Returns per cell (start, stop, weights[stop−start]); Σ over cells = 1 at every index. The
    ramp between adjacent centres spans `overlap` × their distance, centred on the midpoint.
    """
    idx = np.arange(n, dtype=np.float64)
    out = []
    m = len(centers)
    for c in range(m):
        w = np.ones(n)
        if c > 0:
            a, b = centers[c - 1], centers[c]
            mid, half = (a + b) / 2, overlap * (b - a) / 2
            s = np.clip((idx - (mid - half)) / max(2 * half, 1e-9), 0, 1)
            w *= np.sin(0.5 * np.pi * s) ** 2
        if c < m - 1:
            a, b = centers[c], centers[c + 1]
            mid, half = (a + b) / 2, overlap * (b - a) / 2
            s = np.clip((idx - (mid - half)) / max(2 * half, 1e-9), 0, 1)
            w *= np.cos(0.5 * np.pi * s) ** 2
        w[w < 1e-9] = 0.0   # cos(π/2)² is 4e-33 in floating point, not 0: keep the support compact
        nz = np.flatnonzero(w > 0)
        start, stop = int(nz[0]), int(nz[-1]) + 1
        out.append((start, stop, w[start:stop].astype(np.float32)))
    return out


class Deconvolver:
    """Reusable deconvolver: caches FFT plans per padded shape and OTFs per (shape, kernel).

    Parameters
    ----------
    method : "kf" (hyper-Laplacian, default) or "wiener" (one Tikhonov solve).
    alpha : prior exponent for "kf": 1 (soft threshold), 2/3 (default, analytic LUT) or any in (0, 1).
    lam : data weight λ for a unit-range frame (K&F convention). None (default): adapted to each
        frame's noise σ̂, λ = NOISE_LAMBDA[method] / (σ̂ (1 + σ̂/NOISE_KNEE)) — the MAP weight 1/σ²
        for noisy frames, 1/σ for quiet ones, where the measured optima flatten out.
    fft : "auto" (pyFFTW if installed), "fftw" or "scipy".
    workers : FFT threads (1 = one core; run several Deconvolvers in threads for throughput).
    margin : extra padding (px) beyond the kernel size on each axis before rounding to a fast length.
    realtime : never stop to measure an FFTW plan (~0.7 s) for an FFT size the saved wisdom lacks:
        estimate it instead (planned in ~1 ms, runs somewhat slower; counted in `estimated_plans`).
        For the daemon's workers, which warm up the common sizes before going live.

    One instance is not thread-safe (it owns its buffers); numba passes and FFTs release the GIL,
    so one instance per thread scales across cores.
    """

    def __init__(self, method: str = "kf", alpha: float = DEFAULT_ALPHA, lam: float | None = None,
                 fft: str = "auto", workers: int = 1, margin: int = 8, cache_size: int = 16,
                 realtime: bool = False):
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
        self.method, self.alpha, self.lam, self.fft = method, alpha, lam, fft
        self.last_lam = float("nan")   # λ used for the last frame (adaptive when lam is None)
        self.workers, self.margin, self.cache_size = int(workers), int(margin), int(cache_size)
        self.realtime = bool(realtime)
        self.estimated_plans = 0
        self._plans: OrderedDict[tuple[int, int], _Plan] = OrderedDict()
        self._otfs: OrderedDict = OrderedDict()
        self._betas = beta_schedule()
        if method == "kf" and alpha < 1:
            self._luts = [_shrink_lut(alpha, b) for b in self._betas]
            self._taus = [shrink_threshold(alpha, b) for b in self._betas]
        else:
            self._luts = [np.zeros(2, np.float32)] * len(self._betas)
            self._taus = [0.0] * len(self._betas)

    # -------------------------------------------------------------------------- caches
    def padded_shape(self, shape, kshape) -> tuple[int, int]:
        """FFT size for a frame (or tile) of `shape` blurred by a kernel of `kshape`."""
        return (_fast_len(shape[0] + kshape[0] + self.margin), _fast_len(shape[1] + kshape[1] + self.margin))

    def _plan(self, shape) -> _Plan:
        p = self._plans.get(shape)
        if p is None:
            p = self._plans[shape] = _Plan(shape, self.fft, self.workers, measure_unseen=not self.realtime)
            self.estimated_plans += p.estimated
            while len(self._plans) > MAX_PLANS:
                self._plans.popitem(last=False)
        else:
            self._plans.move_to_end(shape)
        return p

    def _otf(self, plan: _Plan, w: np.ndarray, origin) -> tuple[np.ndarray, np.ndarray]:
        """(K, |K|²) with the kernel's origin moved to index (0, 0), so the output is not displaced."""
        key = (plan.shape, origin, w.shape, hash(w.tobytes()))
        hit = self._otfs.get(key)
        if hit is not None:
            self._otfs.move_to_end(key)
            return hit
        hp, wp = plan.shape
        psf = np.zeros(plan.shape, np.float32)
        kh, kw = w.shape
        rows = (np.arange(kh) - origin[0]) % hp
        cols = (np.arange(kw) - origin[1]) % wp
        psf[np.ix_(rows, cols)] = w
        K = scipy.fft.rfft2(psf, workers=self.workers).astype(np.complex64)
        K2 = (K.real * K.real + K.imag * K.imag).astype(np.float32)
        self._otfs[key] = (K, K2)
        while len(self._otfs) > self.cache_size:
            self._otfs.popitem(last=False)
        return K, K2

    # -------------------------------------------------------------------------- solvers
    def lam_for(self, img: np.ndarray, lo: float, hi: float) -> float:
        """λ for this frame: the fixed one, or NOISE_LAMBDA / (σ̂ (1 + σ̂/NOISE_KNEE)), clamped."""
        if self.lam is not None:
            return self.lam
        sigma = noise_sigma(img, (lo, hi))
        a, b = LAMBDA_RANGE[self.method]
        sigma = max(sigma, 1e-9)
        return float(min(max(NOISE_LAMBDA[self.method] / (sigma * (1 + sigma / NOISE_KNEE)), a), b))

    def _solve(self, img, box, w, origin, lo, hi, lam, pshape=None) -> np.ndarray:
        """Deconvolve img[y0:y1, x0:x1] (unit-scaled with lo/hi) → float32 counts of that box."""
        y0, y1, x0, x1 = box
        hh, ww = y1 - y0, x1 - x0
        plan = self._plan(pshape or self.padded_shape((hh, ww), w.shape))
        rng = hi - lo
        _prepare(img, y0, x0, hh, ww, np.float32(lo), np.float32(1.0 / rng), plan.rin)
        K, K2 = self._otf(plan, w, origin)
        kty = plan.spec
        _conj_mul(K, plan.fwd(), kty)
        if self.method == "wiener":
            _wiener(kty, K2, plan.g2, np.float32(1.0 / lam), plan.norm, plan.cin)
            x = plan.inv()
        else:
            x = plan.rin  # the w-step reads x fully before writing div into the same buffer
            mode = 0 if self.alpha == 1.0 else 1
            inv_step = np.float32((_LUT_SIZE - 1) / _LUT_VMAX)
            for beta, lut, tau in zip(self._betas, self._luts, self._taus, strict=True):
                _wstep_div(x, mode, np.float32(1.0 / beta), np.float32(tau), lut, inv_step,
                           np.float32(self.alpha), plan.wx, plan.wy, plan.div, plan.idx)
                _xstep(kty, K2, plan.g2, plan.fwd(), np.float32(beta / lam), plan.norm, plan.cin)
                x = plan.inv()
        out = np.empty((hh, ww), np.float32)
        _finish(x, hh, ww, np.float32(lo), np.float32(rng), out)
        return out

    def run(self, image: np.ndarray, kernel, *, value_range: tuple[float, float] | None = None) -> np.ndarray:
        """Deconvolve a whole frame with one kernel (the paper's method). Counts in, float32 counts out.

        `value_range` (lo, hi) overrides the robust range used for unit scaling (and so λ's scale).
        """
        img = _check_image(image)
        w, origin = _check_kernel(kernel)
        lo, hi = _value_range(img, value_range)
        lam = self.last_lam = self.lam_for(img, lo, hi)
        return self._solve(img, (0, img.shape[0], 0, img.shape[1]), w, origin, lo, hi, lam)

    def run_varying(self, image: np.ndarray, grid, *, overlap: float = 1.0, uniform_tol_px: float = 0.5,
                    value_range: tuple[float, float] | None = None) -> np.ndarray:
        """Spatially varying deconvolution over a kernel grid (``grid.kernels[r][c]``,
        ``grid.centers[r][c] = (y, x)``): one tile per cell, raised-cosine partition-of-unity blend.

        Each tile is its cell's blending support plus a margin of real pixels (the kernel size + 8)
        so that the tile's own boundary effects fall outside the pixels it contributes. When every
        kernel's centroid and spread lie within `uniform_tol_px` of the central kernel's (no roll,
        narrow field of view) the blur is uniform for all practical purposes and the frame is
        solved once with the central kernel (0 disables the shortcut).
        """
        img = _check_image(image)
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
        h, wd = img.shape
        lo, hi = _value_range(img, value_range)
        lam = self.last_lam = self.lam_for(img, lo, hi)   # one λ for every tile: consistent blending
        checked = [[_check_kernel(kernels[r][c], f"grid.kernels[{r}][{c}]") for c in range(nc)]
                   for r in range(nr)]
        d2 = ((centers - np.array([(h - 1) / 2, (wd - 1) / 2])) ** 2).sum(axis=2)
        rc, cc = np.unravel_index(int(np.argmin(d2)), d2.shape)
        if uniform_tol_px > 0 and _max_moment_deviation(checked, checked[rc][cc]) <= uniform_tol_px:
            w, origin = checked[rc][cc]
            return self._solve(img, (0, h, 0, wd), w, origin, lo, hi, lam)
        wys = _tile_weights(h, centers[:, :, 0].mean(axis=1), overlap)
        wxs = _tile_weights(wd, centers[:, :, 1].mean(axis=0), overlap)
        shapes = np.array([w.shape for row in checked for w, _ in row])
        kmax = (int(shapes[:, 0].max()), int(shapes[:, 1].max()))
        m = max(kmax) + 8
        out = np.zeros((h, wd), np.float32)
        boxes = {}
        for r, (ys, ye, _) in enumerate(wys):
            for c, (xs, xe, _) in enumerate(wxs):
                boxes[r, c] = (max(0, ys - m), min(h, ye + m), max(0, xs - m), min(wd, xe + m))
        # every tile padded to one shape: one FFT plan for the frame
        th = max(b[1] - b[0] for b in boxes.values())
        tw = max(b[3] - b[2] for b in boxes.values())
        pshape = self.padded_shape((th, tw), kmax)
        for r, (ys, ye, wy) in enumerate(wys):
            for c, (xs, xe, wx) in enumerate(wxs):
                w, origin = checked[r][c]
                by0, by1, bx0, bx1 = boxes[r, c]
                tile = self._solve(img, boxes[r, c], w, origin, lo, hi, lam, pshape)
                out[ys:ye, xs:xe] += tile[ys - by0:ye - by0, xs - bx0:xe - bx0] * wy[:, None] * wx[None, :]
        return out


def _moments(w: np.ndarray, origin) -> np.ndarray:
    """(mean u_y, mean u_x, std u_y, std u_x) of a kernel (px)."""
    iy, ix = np.indices(w.shape)
    uy = (iy - origin[0]).ravel()
    ux = (ix - origin[1]).ravel()
    p = w.ravel().astype(np.float64)
    p = p / p.sum()
    my, mx = p @ uy, p @ ux
    return np.array([my, mx, math.sqrt(max(p @ (uy - my) ** 2, 0)), math.sqrt(max(p @ (ux - mx) ** 2, 0))])


def _max_moment_deviation(checked, ref) -> float:
    m0 = _moments(*ref)
    return max(float(np.abs(_moments(w, o) - m0).max()) for row in checked for w, o in row)


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
                       lam: float | None = None, overlap: float = 1.0,
                       uniform_tol_px: float = 0.5) -> np.ndarray:
    """Spatially varying deconvolution in overlapping tiles, one kernel per grid cell (float32 counts)."""
    dec = _shared(method, alpha, lam)
    return dec.run_varying(blurry, grid, overlap=overlap, uniform_tol_px=uniform_tol_px)
