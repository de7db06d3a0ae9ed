"""Tiles for spatially varying blur: a raised-cosine partition of unity over the kernel grid, and
the kernel moments that decide when a grid is uniform for all practical purposes."""

from __future__ import annotations

import numpy as np

from .checks import DeconvError, check_kernel

# Real neighbouring pixels around each tile's blending support. Thermal (exponential comet) kernels
# have a local inverse, so tile boundary effects reach a few pixels: 8 px gave the same PSNR on the
# roll-heavy family as the kernel size + 8 (benchmarks/results/deconv.md).
TILE_MARGIN_PX = 8


def tile_weights(n: int, centers: np.ndarray, overlap: float) -> list[tuple[int, int, np.ndarray]]:
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


def stack_kernels(checked) -> tuple[np.ndarray, np.ndarray]:
    """Checked kernels [(weights, origin), …] → (weights zero-padded to one (n, kh, kw) float32
    stack, origins (n, 2)): the form the tile solve and `moments` take."""
    kh = max(w.shape[0] for w, _ in checked)
    kw = max(w.shape[1] for w, _ in checked)
    weights = np.zeros((len(checked), kh, kw), np.float32)
    origins = np.empty((len(checked), 2), np.int64)
    for t, (w, o) in enumerate(checked):
        weights[t, :w.shape[0], :w.shape[1]] = w
        origins[t] = o
    return weights, origins


def moments(weights: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """(mean u_y, mean u_x, std u_y, std u_x) in px of each kernel of a `stack_kernels` stack, (n, 4)."""
    p = weights.astype(np.float64)
    p /= p.sum(axis=(1, 2), keepdims=True)
    out = np.empty((len(p), 4))
    for axis, marginal in ((0, p.sum(axis=2)), (1, p.sum(axis=1))):
        u = np.arange(marginal.shape[1]) - origins[:, axis:axis + 1]   # displacement of each index (px)
        mean = (marginal * u).sum(axis=1)
        out[:, axis] = mean
        out[:, 2 + axis] = np.sqrt(np.maximum((marginal * (u - mean[:, None]) ** 2).sum(axis=1), 0))
    return out


def max_moment_deviation(checked, ref) -> float:
    """Largest difference (px) of any kernel's centroid or spread from those of `ref`."""
    m = moments(*stack_kernels([k for row in checked for k in row]))
    m0 = moments(*stack_kernels([ref]))[0]
    return float(np.abs(m - m0).max())


def kernel_spread(grid) -> float:
    """How far a kernel grid is from one uniform blur (px): the largest difference of any cell's
    kernel centroid or spread (per axis) from the central cell's.

    ≤ 0.5 px: `Deconvolver.run_varying` solves the frame once, as a uniform blur (pure pan/tilt,
    narrow field of view). Roll grows it with the distance from the roll axis; a caller (the
    daemon's governor) can use it to choose uniform vs grid mode, or a finer grid.
    """
    kernels = getattr(grid, "kernels", None)
    centers = getattr(grid, "centers", None)
    if kernels is None or centers is None or len(kernels) == 0:
        raise DeconvError(f"grid: expected an object with .kernels and .centers, got {type(grid).__name__}")
    checked = [[check_kernel(k, f"grid.kernels[{r}][{c}]") for c, k in enumerate(row)]
               for r, row in enumerate(kernels)]
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    mid = c.mean(axis=0)
    i = int(np.argmin(((c - mid) ** 2).sum(axis=1)))
    ncols = len(checked[0])
    return max_moment_deviation(checked, checked[i // ncols][i % ncols])


def central_cell(centers: np.ndarray, shape: tuple[int, int]) -> tuple[int, int]:
    """(row, col) of the grid cell whose centre is nearest the image centre: the kernel a grid whose
    cells all match is solved with (the uniform shortcut)."""
    mid = np.array([(shape[0] - 1) / 2, (shape[1] - 1) / 2])
    d2 = ((np.asarray(centers, np.float64) - mid) ** 2).sum(axis=2)
    r, c = np.unravel_index(int(np.argmin(d2)), d2.shape)
    return int(r), int(c)
