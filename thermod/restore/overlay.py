"""A static overlay burnt into the frames (a maker's logo, OSD text) is kept out of the solve.

The overlay is printed after the optics: the camera's motion does not blur it, so solving it with
the scene's kernel rings around every stroke, into the scene beside it. The solve sees the frame with
the overlay filled in from its surroundings (`fill`: local means of the known pixels over the mask
grown by `GROW_PX`, the encoder's halo around the strokes); the output takes the overlay's own
pixels back from the input (`keep`). The mask is the one the video import found (`motion/overlay`),
or the one the live video source finds (`VideoGyro.overlay`).
"""

from __future__ import annotations

import numpy as np

GROW_PX = 2             # px added around the mask before filling: compression halo around the strokes
FILL_MARGIN_PX = 24    # known pixels around the mask's box that the fill may draw on


def grown(mask: np.ndarray) -> np.ndarray:
    """The mask as filled: grown by `GROW_PX`, uint8 (what `fill` takes)."""
    import cv2

    m = np.asarray(mask, dtype=bool).astype(np.uint8)
    return cv2.dilate(m, np.ones((2 * GROW_PX + 1,) * 2, np.uint8))


def fill(image: np.ndarray, filled_mask: np.ndarray) -> np.ndarray:
    """`image` (float32) with the pixels of `filled_mask` (uint8, from `grown`) filled from their
    surroundings: each the mean of the known pixels in the smallest box (5, 11, 23, … px) that holds
    at least one, so the fill is as smooth as the scene's blur and has no edge of its own. Only the
    mask's bounding box is touched (its cost against OpenCV's Telea: benchmarks/results/video_motion.md)."""
    import cv2

    out = np.array(image, dtype=np.float32, copy=True)
    bx, by, bw, bh = cv2.boundingRect(np.asarray(filled_mask, dtype=np.uint8))
    if bw == 0:
        return out
    h, w = out.shape
    y0, y1 = max(0, by - FILL_MARGIN_PX), min(h, by + bh + FILL_MARGIN_PX)
    x0, x1 = max(0, bx - FILL_MARGIN_PX), min(w, bx + bw + FILL_MARGIN_PX)
    crop = out[y0:y1, x0:x1]
    todo = np.asarray(filled_mask[y0:y1, x0:x1], dtype=bool)
    known = (~todo).astype(np.float32)
    if not known.any():
        return out                              # the whole frame is overlay: nothing to fill from
    k = 5
    while todo.any():
        num = cv2.boxFilter(crop * known, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
        den = cv2.boxFilter(known, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
        ok = todo & (den > 0.5)
        crop[ok] = num[ok] / den[ok]
        todo &= ~ok
        k = 2 * k + 1
    return out


def keep(restored: np.ndarray, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """`restored` with the overlay's pixels (`mask`) taken from the input `image`."""
    out = np.array(restored, dtype=np.float32, copy=True)
    m = np.asarray(mask, dtype=bool)
    out[m] = np.asarray(image)[m]
    return out
