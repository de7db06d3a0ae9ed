"""What the kernel renderer produces: a `Kernel`, the `KernelPath` behind it, a `KernelGrid`."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numba import njit

from thermod.errors import ThermodError

__all__ = ["Kernel", "KernelError", "KernelGrid", "KernelPath"]


@njit(cache=True, nogil=True)
def _max_radius(w, oy, ox):
    """max √((i − oy)² + (j − ox)²) over the non-zero w[i, j] (0 when all are zero): one pass, no
    index arrays (the daemon asks it of every cell of a grid, every frame)."""
    best = 0
    for i in range(w.shape[0]):
        for j in range(w.shape[1]):
            if w[i, j] != 0:
                d = (i - oy) * (i - oy) + (j - ox) * (j - ox)
                if d > best:
                    best = d
    return np.sqrt(best)


class KernelError(ThermodError, ValueError):
    """Bad input to a kernel renderer (names the argument), or a motion no kernel can represent."""


@dataclass(frozen=True, eq=False)
class Kernel:
    """A discrete blur kernel: B(p) = Σ_u k(u) S(p − u) with k(u) = weights[oy + u_y, ox + u_x].

    Attributes
    ----------
    weights : float32 [kh, kw], sums to 1.
    origin : (oy, ox), the array index of zero displacement.
    coverage : fraction of the window's weight (5τ, or the exposure) covered by gyro samples;
        < 1 means the rate was held constant beyond the first/last sample.
    n_samples : gyro samples inside the window.
    """

    weights: np.ndarray
    origin: tuple[int, int]
    coverage: float = 1.0
    n_samples: int = 0

    def __post_init__(self):
        w = self.weights
        if not isinstance(w, np.ndarray) or w.dtype != np.float32:
            w = np.asarray(w, dtype=np.float32)
            object.__setattr__(self, "weights", w)
        if w.ndim != 2 or w.size == 0:
            raise KernelError(f"Kernel.weights: expected a non-empty 2-D array, got shape {w.shape}")
        try:
            oy, ox = (int(o) for o in self.origin)
        except (TypeError, ValueError):
            raise KernelError(f"Kernel.origin: expected (oy, ox) integers, got {self.origin!r}") from None
        if not (0 <= oy < w.shape[0] and 0 <= ox < w.shape[1]):
            raise KernelError(f"Kernel.origin: {self.origin!r} lies outside weights of shape {w.shape}")
        object.__setattr__(self, "origin", (oy, ox))

    @functools.cached_property
    def extent_px(self) -> float:
        """max |u| over the non-zero weights (px)."""
        return float(_max_radius(self.weights, self.origin[0], self.origin[1]))

    @functools.cached_property
    def centroid(self) -> tuple[float, float]:
        """Mean displacement (u_y, u_x) = Σ_u k(u) u (px)."""
        w = self.weights.astype(np.float64)
        iy, ix = np.indices(w.shape)
        s = w.sum()
        return (float((w * (iy - self.origin[0])).sum() / s), float((w * (ix - self.origin[1])).sum() / s))

    @property
    def shape(self) -> tuple[int, int]:
        return self.weights.shape


@dataclass(frozen=True, eq=False)
class KernelPath:
    """The sampled image path of one pixel before splatting: node times, offsets and weights.

    `t` (camera clock, s), `u` float64 [n, 2] offsets (u_x, u_y) in px, `w` float64 [n] normalised
    quadrature weights (sum 1). Splatting `w` at `u` bilinearly gives the kernel without PSF.
    """

    t: np.ndarray
    u: np.ndarray
    w: np.ndarray
    coverage: float
    n_samples: int


@dataclass(frozen=True, eq=False)
class KernelGrid:
    """One kernel per cell of a rows × cols grid over the image (spatially varying blur).

    `kernels[r][c]` is rendered at the cell centre `centers[r, c] = (y, x)`; `bounds[r, c]` =
    (y0, y1, x0, x1), half-open pixel bounds of the cell; `times[r]` is the read time used for the
    cells of row r (rolling readout); `image_shape` = (H, W).
    """

    kernels: list
    centers: np.ndarray
    bounds: np.ndarray
    times: np.ndarray
    image_shape: tuple[int, int]
    kind: str = "thermal"

    @property
    def grid(self) -> tuple[int, int]:
        return self.centers.shape[0], self.centers.shape[1]

    @property
    def coverage(self) -> float:
        return min(k.coverage for row in self.kernels for k in row)

    @property
    def max_extent_px(self) -> float:
        return max(k.extent_px for row in self.kernels for k in row)

    @property
    def common_frame(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """(origin, (kh, kw)) of the smallest array holding every cell on one shared origin (cells keep
        their displacements): the shape a grid travels in (`thermod.io.wire.pack_kernel`) and the
        ``kernel_size`` a frame deblurred with it reports. Larger than the largest cell when the cells'
        origins differ."""
        flat = [k for row in self.kernels for k in row]
        oy = max(k.origin[0] for k in flat)
        ox = max(k.origin[1] for k in flat)
        kh = oy + max(k.weights.shape[0] - k.origin[0] for k in flat)
        kw = ox + max(k.weights.shape[1] - k.origin[1] for k in flat)
        return (int(oy), int(ox)), (int(kh), int(kw))

    def kernel_at(self, y: float, x: float) -> Kernel:
        """The kernel of the cell containing pixel (y, x)."""
        r = int(np.clip(np.searchsorted(self.bounds[:, 0, 1], y, side="right"), 0, self.grid[0] - 1))
        c = int(np.clip(np.searchsorted(self.bounds[0, :, 3], x, side="right"), 0, self.grid[1] - 1))
        return self.kernels[r][c]
