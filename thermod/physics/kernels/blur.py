"""The forward model B(p) = Σ_u k(u) S(p − u), with one kernel or a spatially varying grid."""

from __future__ import annotations

import cv2
import numpy as np

from thermod.physics.kernels.types import Kernel, KernelError, KernelGrid

__all__ = ["blur", "blur_varying"]


def _as_image(image, name="image") -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 2 or img.shape[0] == 0 or img.shape[1] == 0:
        raise KernelError(f"{name}: expected a non-empty 2-D array [H, W], got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.floating) or np.issubdtype(img.dtype, np.integer)):
        raise KernelError(f"{name}: expected a numeric image, got dtype {img.dtype}")
    return np.ascontiguousarray(img, dtype=np.float32)


def _check_kernel(kernel) -> Kernel:
    if not isinstance(kernel, Kernel):
        raise KernelError(f"kernel: expected a thermod.physics.kernels.Kernel, got {type(kernel).__name__}")
    return kernel   # shape and origin were checked when it was made


def _filter(img: np.ndarray, kernel: Kernel, border: int) -> np.ndarray:
    w = kernel.weights
    kh, kw = w.shape
    oy, ox = kernel.origin
    flipped = np.ascontiguousarray(w[::-1, ::-1], dtype=np.float32)
    # correlation with the flipped kernel anchored at (kw−1−ox, kh−1−oy) is B(p) = Σ_u k(u) S(p − u)
    return cv2.filter2D(img, cv2.CV_32F, flipped, anchor=(kw - 1 - ox, kh - 1 - oy), borderType=border)


def blur(image, kernel: Kernel) -> np.ndarray:
    """The forward model B(p) = Σ_u k(u) S(p − u) (float32 out, replicate border)."""
    img = _as_image(image)
    return _filter(img, _check_kernel(kernel), cv2.BORDER_REPLICATE)


def _tents(centers: np.ndarray, n: int) -> np.ndarray:
    """Partition-of-unity hat weights [len(centers), n] along one axis, flat beyond the end centres."""
    x = np.arange(n, dtype=np.float64)
    k = len(centers)
    out = np.zeros((k, n))
    if k == 1:
        out[0] = 1.0
        return out
    for i, c in enumerate(centers):
        if i > 0:
            lo = centers[i - 1]
            sel = (x >= lo) & (x <= c)
            out[i, sel] = (x[sel] - lo) / (c - lo)
        else:
            out[i, x <= c] = 1.0
        if i < k - 1:
            hi = centers[i + 1]
            sel = (x > c) & (x < hi)
            out[i, sel] = (hi - x[sel]) / (hi - c)
        else:
            out[i, x > c] = 1.0
    return out


def blur_varying(image, grid: KernelGrid) -> np.ndarray:
    """Spatially varying forward model: per-cell blurs blended with bilinear (tent) weights.

    Between cell centres the weights fall linearly from one cell to the next (a partition of
    unity), so the blur changes smoothly; a uniform grid reproduces `blur` exactly.
    """
    img = _as_image(image)
    if not isinstance(grid, KernelGrid):
        raise KernelError(f"grid: expected a thermod.physics.kernels.KernelGrid, got {type(grid).__name__}")
    h, w = img.shape
    if tuple(grid.image_shape) != (h, w):
        raise KernelError(f"grid: rendered for images of shape {tuple(grid.image_shape)}, image is {(h, w)}")
    rows, cols = grid.grid
    for row in grid.kernels:
        for k in row:
            _check_kernel(k)
    pad = max(max(k.weights.shape) for row in grid.kernels for k in row)
    padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    ty = _tents(grid.centers[:, 0, 0], h)
    tx = _tents(grid.centers[0, :, 1], w)
    out = np.zeros((h, w), dtype=np.float32)
    for i in range(rows):
        ys = np.nonzero(ty[i])[0]
        y0, y1 = int(ys[0]), int(ys[-1]) + 1
        for j in range(cols):
            xs = np.nonzero(tx[j])[0]
            x0, x1 = int(xs[0]), int(xs[-1]) + 1
            crop = padded[y0:y1 + 2 * pad, x0:x1 + 2 * pad]
            # the crop extends `pad` beyond the region, so its own border never reaches the result
            b = _filter(crop, grid.kernels[i][j], cv2.BORDER_REPLICATE)[pad:pad + y1 - y0, pad:pad + x1 - x0]
            wgt = (ty[i, y0:y1, None] * tx[j, None, x0:x1]).astype(np.float32)
            out[y0:y1, x0:x1] += wgt * b
    return out
