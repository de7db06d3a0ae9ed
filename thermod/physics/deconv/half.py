"""Deconvolution at half resolution: the cheapest way to remove a blur, for a machine short of CPU.

The frame is averaged over 2×2 blocks (a pixel of the half frame sits at ((2i + ½), (2j + ½)) of the
full one), the kernel's displacements are halved (each weight splatted bilinearly at u/2), the half
frame is solved by the wrapped `Deconvolver`, and the result is brought back to full size
bilinearly. The solve costs 0.3–0.4× the full one (a quarter of the FFT points, plus the
resampling); what it gives up is the detail above
half the Nyquist frequency, where a thermal frame's blur and noise leave least anyway. The daemon's
governor runs it as its last rung (``wiener_half``), below Wiener at full resolution and above
passing a frame through raw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .checks import check_image, check_kernel
from .solver import Deconvolver


@dataclass(frozen=True)
class _HalfKernel:
    """Duck-typed `thermod.physics.kernels.Kernel` (weights, origin) on the half grid."""

    weights: np.ndarray
    origin: tuple[int, int]


def halve_kernel(kernel) -> _HalfKernel:
    """The kernel of the 2×2-averaged frame: each weight at displacement u splatted bilinearly at u/2
    (a 2×2 mean of a blurred frame is the 2×2 mean of the sharp one, blurred by the same motion, which
    moves half as many of its pixels). Weights sum to 1."""
    w, (oy, ox) = check_kernel(kernel)
    iy, ix = np.nonzero(w)
    vals = w[iy, ix].astype(np.float64)
    y, x = (iy - oy) / 2.0, (ix - ox) / 2.0
    y0, x0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    fy, fx = y - y0, x - x0
    oy2, ox2 = -int(y0.min()), -int(x0.min())
    out = np.zeros((int(y0.max()) + oy2 + 2, int(x0.max()) + ox2 + 2), np.float64)
    for dy, dx, share in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx), (1, 0, fy * (1 - fx)),
                          (1, 1, fy * fx)):
        np.add.at(out, (y0 + oy2 + dy, x0 + ox2 + dx), vals * share)
    out /= out.sum()
    return _HalfKernel(out.astype(np.float32), (oy2, ox2))


@dataclass(frozen=True)
class _HalfGrid:
    """Duck-typed `thermod.physics.kernels.KernelGrid` on the half grid: each cell's kernel halved, its
    centre at (y − ½) / 2, (x − ½) / 2 (where the full pixel (y, x) falls among the half ones)."""

    kernels: list
    centers: np.ndarray

    @classmethod
    def of(cls, grid) -> _HalfGrid:
        centers = (np.asarray(grid.centers, np.float64) - 0.5) / 2.0
        return cls([[halve_kernel(k) for k in row] for row in grid.kernels], centers)


class HalfResolution:
    """A `Deconvolver` run on the 2×2-averaged frame (see the module docstring).

    ``run(image, kernel)`` and ``run_varying(image, grid)`` (each cell's kernel halved) return
    float32 counts of the full frame.
    """

    def __init__(self, single: Deconvolver | None = None):
        self.single = single or Deconvolver(method="wiener")
        self.last_cells = 1

    def __getattr__(self, name):              # λ, σ̂, plans: the wrapped solver's
        return getattr(self.single, name)

    def run(self, image, kernel, *, value_range=None) -> np.ndarray:
        return self._solved_at_half(image, lambda half: self.single.run(
            half, halve_kernel(kernel), value_range=value_range))

    def run_varying(self, image, grid, *, value_range=None, uniform_tol_px: float = 0.5, **kw) -> np.ndarray:
        """The half frame solved over `grid`'s kernels, each halved, at its cells' centres on the half
        grid; `uniform_tol_px` stays a full-frame tolerance."""
        return self._solved_at_half(image, lambda half: self.single.run_varying(
            half, _HalfGrid.of(grid), value_range=value_range, uniform_tol_px=0.5 * uniform_tol_px, **kw))

    def _solved_at_half(self, image, solve) -> np.ndarray:
        """`solve` on the 2×2-averaged frame, its result brought back to the frame's size."""
        img = check_image(image)
        h, w = img.shape
        h2, w2 = max(1, h // 2), max(1, w // 2)
        out = solve(cv2.resize(img[:2 * h2, :2 * w2], (w2, h2), interpolation=cv2.INTER_AREA))
        self.last_cells = self.single.last_cells
        return cv2.resize(np.asarray(out, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)

    def padded_shape(self, shape, kshape) -> tuple[int, int]:
        """The wrapped solver's FFT size for the half frame (warm-up builds these plans)."""
        return self.single.padded_shape((shape[0] // 2, shape[1] // 2),
                                        (math.ceil(kshape[0] / 2) + 2, math.ceil(kshape[1] / 2) + 2))
