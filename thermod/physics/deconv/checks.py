"""Argument checks of the deconvolver: every bad input becomes a `DeconvError` naming it."""

from __future__ import annotations

import math

import numpy as np

from thermod.errors import ThermodError


class DeconvError(ThermodError):
    """Bad arguments to the deconvolver (names the argument and what was expected)."""


def check_kernel(kernel, name="kernel"):
    w = getattr(kernel, "weights", None)
    origin = getattr(kernel, "origin", None)
    if w is None or origin is None:
        raise DeconvError(f"{name}: expected an object with .weights and .origin, "
                          f"got {type(kernel).__name__}")
    w = np.asarray(w)
    if w.ndim != 2 or w.size == 0:
        raise DeconvError(f"{name}.weights: expected a non-empty 2-D array, got shape {w.shape}")
    if not np.issubdtype(w.dtype, np.floating) and not np.issubdtype(w.dtype, np.integer):
        raise DeconvError(f"{name}.weights: expected real numbers, got dtype {w.dtype}")
    w = w.astype(np.float32, copy=False)
    if not np.all(np.isfinite(w)):
        raise DeconvError(f"{name}.weights: contains NaN or infinite values")
    s = float(w.sum(dtype=np.float64))
    if not s > 0:
        raise DeconvError(f"{name}.weights: must sum to a positive value (≈1), got {s}")
    try:
        oy, ox = (int(v) for v in origin)
    except (TypeError, ValueError):
        raise DeconvError(f"{name}.origin: expected (oy, ox) integers, got {origin!r}") from None
    if not (0 <= oy < w.shape[0] and 0 <= ox < w.shape[1]):
        raise DeconvError(f"{name}.origin: {(oy, ox)} lies outside the weights of shape {w.shape}")
    if abs(s - 1.0) > 1e-3:
        w = w / np.float32(s)
    return w, (oy, ox)


def check_image(image):
    a = np.asarray(image)
    if a.ndim != 2 or min(a.shape) < 2:
        raise DeconvError(f"image: expected a 2-D frame of at least 2×2 pixels, got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise DeconvError(f"image: expected numeric counts, got dtype {a.dtype}")
    if np.issubdtype(a.dtype, np.floating):
        if a.dtype != np.float32:
            a = a.astype(np.float32)
        if not np.isfinite(a[::7, ::7]).all() or not np.isfinite(a).all():
            raise DeconvError("image: contains NaN or infinite values")
    elif a.dtype not in (np.uint16, np.int32, np.uint8, np.int16):
        a = a.astype(np.float32)
    return a


def check_frame(frame, calib, t_frame) -> tuple[np.ndarray, float]:
    """A stream frame as float32 counts of the calibration's size, and its finite read time (s)."""
    img = check_image(frame)
    if img.shape != (int(calib.height), int(calib.width)):
        raise DeconvError(f"frame: expected {int(calib.height)}×{int(calib.width)} "
                          f"(the calibration's), got {img.shape[0]}×{img.shape[1]}")
    t_frame = float(t_frame)
    if not math.isfinite(t_frame):
        raise DeconvError(f"t_frame: expected a finite time (s), got {t_frame}")
    return np.asarray(img, np.float32), t_frame
