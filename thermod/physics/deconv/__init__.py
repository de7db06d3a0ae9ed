"""Non-blind deconvolution of thermal frames: Krishnan & Fergus hyper-Laplacian, Wiener, tiles.

Forward model (docs/design.md §1, Eq. 11/18): ``B(p) = Σ_u k(u) S(p − u)`` with the kernel given as
``weights[oy + u_y, ox + u_x]`` and ``origin = (oy, ox)`` the index of zero displacement (not the
array centre: comet-tail kernels are one-sided). Any object with ``weights`` and ``origin``
works (duck-typed ``thermod.physics.kernels.Kernel``).

Krishnan & Fergus 2009, "Fast image deconvolution using hyper-Laplacian priors" (K&F)::

    min_x  (λ/2) ||k ⊛ x − y||²  +  Σ_j |∇_j x|^α                       (K&F Eq. 1)

by half-quadratic splitting: auxiliary ``w ≈ ∇x`` with penalty ``(β/2)||w − ∇x||²``, β from 1 to
256 by ×2√2 (six steps, one inner iteration each, as in their code).

- w-step (`wstep`): per pixel ``min_w |w|^α + (β/2)(w − v)²``: soft threshold (α = 1), K&F's
  analytic quartic root (α = 2/3) or Newton (other α), through a lookup table per β.
- x-step (`xstep`): closed form in the Fourier domain,
  ``X = (K̄·Y + (β/λ) F(∇ᵀw)) / (|K|² + (β/λ)(|F∂x|² + |F∂y|²))``.

**λ convention (K&F's):** λ weights the *data* term for an image scaled to a unit range; the
paper's "λ = 0.001–0.003" prior weight is 1/λ here. Raw counts are mapped to that range by the
frame's robust range (0.5–99.5 percentiles → 0–1, `robust_range`); results come back in the
input's counts, float32, never clipped.

Wiener fast path: one Tikhonov solve with a gradient prior, ``X = K̄Y / (|K|² + (1/λ)|F∇|²)``.

Boundaries (`xstep`): a raised-cosine periodic extension to an FFT-friendly size at least the kernel
size larger per axis, so any kernel size (100+ px) works and no ringing frame appears. FFTs
(`plans`): pyFFTW float32 plans with wisdom kept on disk, else scipy.fft. λ from the frame's
noise: `noise`.

Spatially varying blur (`deconvolve_varying`): each cell of a kernel grid is deconvolved in its
own tile (the cell's blending support plus `margin_px` = `TILE_MARGIN_PX` = 8 real neighbouring
pixels: a thermal kernel's inverse is local), and tiles are blended with separable raised-cosine
weights that form a partition of unity, so there are no seams. The tiles of a frame share one FFT
size and are solved in stacks of a few (one FFTW call and one numba pass per K&F step for the
whole stack, `plans.Plan` with a 3-D shape). A grid whose kernels all match
the central one (`kernel_spread(grid)` ≤ 0.5 px: pure pan/tilt with a narrow field of view) is
solved once, as a uniform blur.

Knobs for a caller that must fit a time budget (the daemon's governor); their measured costs and
PSNR are in benchmarks/results/deconv.md:

- the grid (rendered by the caller) and ``run_varying(overlap=…)``: every pixel is solved
  (1 + overlap)² times, so cost grows with overlap in steps of the tiles' FFT size, and quality with
  both grid size and overlap. ``last_cells`` after a solve: the cells it solved (1: the uniform
  shortcut).
- `kernel_spread(grid)`: 0 for a uniform grid; use the uniform solve when it is small.
- ``Deconvolver(iterations=n)``: K&F's continuation from β = 1 in n coarser steps instead of six
  (n = 3: β = 1, 8, 64); cost ≈ n/6 of the solve's FFT work. Starting from β = 1 matters: keeping
  only the last n steps of the six loses far more.
- ``Deconvolver(split=(2, 2))``: large sensors — a uniform-blur frame solved in 2×2 cache-sized
  tiles, which keeps the FFTs in cache.
- ``method="wiener"``: one Tikhonov solve per tile or frame, a fraction of a K&F solve.

Modules: `wstep` (shrinkage, lookup tables), `xstep` (Fourier-domain solves, boundary extension),
`plans` (FFT plans, FFTW wisdom), `noise` (robust range, σ̂, λ from noise), `tiles` (partition of
unity, uniform-grid test), `checks` (argument errors), `solver` (`Deconvolver`, `deconvolve`,
`deconvolve_varying`), `temporal` (`TemporalDeconvolver`: frame t from t−N…t, gyro-warped, one
kernel per view, weights falling where the views disagree; imported on its own, it needs OpenCV),
`recursive` (`RecursiveDeconvolver`: frame t's Wiener solve corrected by the gyro-warped previous
result, a Kalman update per spatial frequency: the daemon's temporal rung; OpenCV too).
"""

from .checks import DeconvError
from .noise import (
    KF_HYPER_LAPLACIAN,
    LAMBDA_RANGE,
    NOISE_KNEE,
    NOISE_LAMBDA,
    RANGE_PERCENTILES,
    NoiseLambda,
    noise_sigma,
    robust_range,
)
from .plans import MAX_PLANS, PLANNING_TIMELIMIT_S, wisdom_path
from .solver import DEFAULT_ALPHA, TILE_OVERLAP, Deconvolver, deconvolve, deconvolve_varying
from .tiles import TILE_MARGIN_PX, kernel_spread
from .wstep import (
    BETA_MAX,
    BETA_RATE,
    BETA_START,
    beta_schedule,
    shrink_23_analytic,
    shrink_numeric,
    shrink_threshold,
)

__all__ = [
    "BETA_MAX", "BETA_RATE", "BETA_START", "DEFAULT_ALPHA", "KF_HYPER_LAPLACIAN", "LAMBDA_RANGE", "MAX_PLANS",
    "NOISE_KNEE",
    "NOISE_LAMBDA", "PLANNING_TIMELIMIT_S", "RANGE_PERCENTILES", "DeconvError", "Deconvolver",
    "NoiseLambda", "TILE_MARGIN_PX", "TILE_OVERLAP", "beta_schedule", "deconvolve", "deconvolve_varying",
    "kernel_spread",
    "noise_sigma", "robust_range",
    "shrink_23_analytic", "shrink_numeric", "shrink_threshold", "wisdom_path",
]
