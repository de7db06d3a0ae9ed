"""Counts → 8-bit pictures, the one mapping every live view uses (RTSP, the browser page, watch PNGs).

`to_u8` is the linear map of a range to 0‥255; `Agc` picks that range from robust percentiles of
each frame (optionally smoothed over time so the brightness does not pump); `side_by_side` shows
raw | deblurred through the raw's range, so the same counts give the same grey on both sides.
"""

from __future__ import annotations

import math

import numpy as np


def to_u8(image: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Linear map of [lo, hi] to 0‥255, saturating outside (NaN → 0); a flat range maps to black."""
    scale = 255.0 / (hi - lo) if hi - lo > 1e-6 * max(1.0, abs(lo)) else 0.0
    out = np.subtract(image, np.float32(lo), dtype=np.float32)   # in place from here: 50 fps
    out *= np.float32(scale)
    out += np.float32(0.5)
    np.fmax(out, 0.0, out=out)           # fmax also maps NaN to 0
    np.minimum(out, 255.0, out=out)
    return out.astype(np.uint8)


class Agc:
    """Automatic gain control: counts → 0‥255, linear between robust percentiles of each frame.

    ``low_pct``/``high_pct`` of a subsample (every ``step``-th pixel each way, so a few hot pixels
    cannot set the range) map to 0 and 255, values outside saturate. ``smoothing`` is the weight of the
    previous range in an exponential filter of (lo, hi), so the brightness does not pump frame to frame.
    """

    def __init__(self, low_pct: float = 1.0, high_pct: float = 99.0, smoothing: float = 0.0,
                 max_samples: int = 20000):
        if not 0.0 <= low_pct < high_pct <= 100.0:
            raise ValueError(f"AGC percentiles: expected 0 <= low < high <= 100, got {low_pct}, {high_pct}")
        if not 0.0 <= smoothing < 1.0:
            raise ValueError(f"AGC smoothing: expected a value in [0, 1), got {smoothing}")
        self.pcts = (float(low_pct), float(high_pct))
        self.smoothing = float(smoothing)
        self.max_samples = max_samples
        self.range: tuple[float, float] | None = None

    def update(self, image: np.ndarray) -> tuple[float, float]:
        """Fold `image`'s percentiles into the running range and return it."""
        step = max(1, int(math.sqrt(image.size / self.max_samples)))
        sub = np.asarray(image[::step, ::step], np.float32)
        finite = sub[np.isfinite(sub)]
        if finite.size == 0:
            return self.range or (0.0, 1.0)
        lo, hi = (float(v) for v in np.percentile(finite, self.pcts))
        if self.range is not None and self.smoothing > 0:
            a = self.smoothing
            lo, hi = a * self.range[0] + (1 - a) * lo, a * self.range[1] + (1 - a) * hi
        self.range = (lo, hi)
        return lo, hi

    apply = staticmethod(to_u8)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return self.apply(image, *self.update(image))


def side_by_side(raw: np.ndarray | None, frame: np.ndarray, agc: Agc | None = None,
                 gap: int = 0) -> np.ndarray:
    """raw | frame as 8-bit, both through the range `agc` takes from the raw (the frame alone when no
    raw of the same shape is there), separated by `gap` black columns."""
    agc = agc or Agc()
    if raw is None or raw.shape != frame.shape:
        return agc(frame)
    lo, hi = agc.update(raw)
    out = np.zeros((frame.shape[0], 2 * frame.shape[1] + gap), np.uint8)
    out[:, : frame.shape[1]] = to_u8(raw, lo, hi)
    out[:, frame.shape[1] + gap:] = to_u8(frame, lo, hi)
    return out
