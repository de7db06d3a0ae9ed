"""Blur kernels from the gyro: thermal (Eq. 18), photon (Eq. 17), optical PSF (Eq. 19), grids.

A microbolometer frame read at t_k is the exponential average of the sharp views S(s) over the
past (Eq. 11), so for a pure camera rotation it is the sharp view at t_k blurred by

    B(p) = Σ_u k(u) S_k(p − u),   k(u) = ∫ w(s) δ(u − u(s)) ds,   w(s) ∝ exp(−(t_k − s)/τ),

with u(s) = p − π(K Q(s) K⁻¹ p) and Q(s) = R(t_k)ᵀ R(s) (Eq. 16). The gyro gives ω at ~1 kHz;
between samples the rate is piecewise linear (exactly `thermod.physics.geometry.integrate_rotations`).
The path is subdivided so that consecutive splats are < 0.5 px apart — splatting only at the gyro
stamps would give a dotted kernel at high rates ("stepping", Eq. 12) — and each sub-interval's
weight is the exact integral of the exponential (or of the box, for a photon detector, Eq. 17)
against the linear "hat" between its end points, so a straight path gets its exact first moment.
Each node is splatted bilinearly, the kernel is normalised to 1 and optionally convolved with the
optical PSF (Eq. 19). Kernels are as large as the motion needs: never cropped.


Layout: `types` (Kernel, KernelPath, KernelGrid), `params` (calibration → renderer parameters,
input checks, window and sampling bounds), `core` (the numba renderer), `render` (the public
renderers and the optical PSF), `blur` (the forward model). The plain NumPy reference the tests
hold the fast renderer to lives in sim/reference_kernels.py, independent of all of these.
"""

from thermod.physics.kernels.blur import blur, blur_varying
from thermod.physics.kernels.core import PathStatus
from thermod.physics.kernels.params import MAX_NODES, MAX_STEP_PX
from thermod.physics.kernels.render import (
    optical_psf,
    render_kernel_grid,
    render_path,
    render_photon_kernel,
    render_thermal_kernel,
)
from thermod.physics.kernels.types import Kernel, KernelError, KernelGrid, KernelPath

__all__ = [
    "Kernel", "KernelGrid", "KernelPath", "KernelError", "PathStatus", "MAX_STEP_PX", "MAX_NODES",
    "render_thermal_kernel", "render_photon_kernel", "render_kernel_grid", "render_path",
    "optical_psf", "blur", "blur_varying",
]
