"""Non-blind deconvolution of thermal frames: Krishnan & Fergus hyper-Laplacian, Wiener, tiles.

Forward model (DESIGN.md §1, Eq. 11/18): ``B(p) = Σ_u k(u) S(p − u)`` with the kernel given as
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
own tile (the cell's blending support plus a margin of real neighbouring pixels), and tiles are
blended with separable raised-cosine weights that form a partition of unity, so there are no
seams. A grid whose kernels all match the central one (centroid and spread within 0.5 px: pure
pan/tilt with a narrow field of view) is solved once, as a uniform blur.

Modules: `wstep` (shrinkage, lookup tables), `xstep` (Fourier-domain solves, boundary extension),
`plans` (FFT plans, FFTW wisdom), `noise` (robust range, σ̂, λ from noise), `tiles` (partition of
unity, uniform-grid test), `checks` (argument errors), `solver` (`Deconvolver`, `deconvolve`,
`deconvolve_varying`).
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
from .solver import DEFAULT_ALPHA, Deconvolver, deconvolve, deconvolve_varying
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
    "NOISE_KNEE", "NOISE_LAMBDA", "PLANNING_TIMELIMIT_S", "RANGE_PERCENTILES", "DeconvError", "Deconvolver",
    "NoiseLambda", "beta_schedule", "deconvolve", "deconvolve_varying", "noise_sigma", "robust_range",
    "shrink_23_analytic", "shrink_numeric", "shrink_threshold", "wisdom_path",
]
