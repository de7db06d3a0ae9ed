"""A static overlay burnt into the frames (a maker's logo, OSD text) is kept out of the solve.

The overlay is printed after the optics: the camera's motion does not blur it, so solving it with
the scene's kernel rings around every stroke, into the scene beside it. The solve sees the frame with
the overlay filled in from its surroundings (`fill`: OpenCV's Telea inpainting over the mask grown
by `GROW_PX`, the encoder's halo around the strokes); the output takes the overlay's own pixels back
from the input (`keep`). The mask is the one the video import found (`motion/overlay`).
"""

from __future__ import annotations

import numpy as np

GROW_PX = 2             # px added around the mask before filling: compression halo around the strokes
INPAINT_RADIUS_PX = 3


def grown(mask: np.ndarray) -> np.ndarray:
    """The mask as filled: grown by `GROW_PX`, uint8 (what `fill` takes)."""
    import cv2

    m = np.asarray(mask, dtype=bool).astype(np.uint8)
    return cv2.dilate(m, np.ones((2 * GROW_PX + 1,) * 2, np.uint8))


def fill(image: np.ndarray, filled_mask: np.ndarray) -> np.ndarray:
    """`image` (float32) with the pixels of `filled_mask` (uint8, from `grown`) inpainted from their
    surroundings."""
    import cv2

    return cv2.inpaint(np.asarray(image, dtype=np.float32), filled_mask, INPAINT_RADIUS_PX, cv2.INPAINT_TELEA)


def keep(restored: np.ndarray, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """`restored` with the overlay's pixels (`mask`) taken from the input `image`."""
    out = np.array(restored, dtype=np.float32, copy=True)
    m = np.asarray(mask, dtype=bool)
    out[m] = np.asarray(image)[m]
    return out
