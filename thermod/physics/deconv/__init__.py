"""Non-blind deconvolution of thermal frames: Krishnan & Fergus hyper-Laplacian, Wiener, tiles.

Forward model (Eq. 11/18): ``B(p) = Σ_u k(u) S(p − u)`` with the kernel given as
``weights[oy + u_y, ox + u_x]`` and ``origin = (oy, ox)`` the index of zero displacement (not the
array centre: comet-tail kernels are one-sided). Any object with ``weights`` and ``origin`` works
(duck-typed ``thermod.physics.kernels.Kernel``).

K&F minimises ``(λ/2)||k ⊛ x − y||² + Σ_j |∇_j x|^α`` by half-quadratic splitting (β from 1 to 256
by ×2√2); λ weights the *data* term of the frame scaled to a unit range by its robust range, and
results come back in the input's counts, float32, never clipped. ``method="wiener"`` is one Tikhonov
solve. A kernel grid is solved in tiles blended by a partition of unity; a grid whose kernels all
match the central one (`kernel_spread` ≤ 0.5 px) is solved once, as a uniform blur. The derivation,
the λ rule, the borders, the tiles and the knobs for a time budget: docs/design.md §1.5; their costs
and PSNR: benchmarks/results/deconv.md.

Modules: `wstep` (shrinkage), `xstep` (Fourier-domain solves, boundary extension), `plans` (FFT
plans, FFTW wisdom), `noise` (robust range, σ̂, λ from noise), `tiles` (partition of unity),
`checks` (argument errors), `solver` (`Deconvolver`, `deconvolve`, `deconvolve_varying`), `temporal`
(`TemporalDeconvolver`, the joint solve over frames t−N…t) and `recursive` (`RecursiveDeconvolver`,
the daemon's temporal rung); the last two need OpenCV.
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
