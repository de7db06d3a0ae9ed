"""Unit scaling and the noise-adaptive λ.

Raw counts are mapped to a unit range by the frame's robust range (0.5–99.5 percentiles → 0–1,
`robust_range`); `noise_sigma` measures the temporal noise σ̂ in that range, and
`NoiseLambda` turns it into the K&F data weight λ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .checks import DeconvError, check_image

# Defaults of `NoiseLambda` per method (K&F: for the default α = 1). Fitted on simulated SBTI frames of
# six real scenes at 6.25–100 °/s and NETD 30 and 100 mK (α = 1: best λ 950–3000 at σ̂ = 0.003,
# 9500–40000 at σ̂ = 0.0006, ≤ 300–950 at σ̂ = 0.01); benchmarks/bench_quality.py refits them on
# half of its scenes and reports the others.
NOISE_LAMBDA = {"kf": 8.5, "wiener": 0.6}
NOISE_KNEE = 0.012
# K&F with α < 1 (hyper-Laplacian): the w-step zeroes small gradients outright, so it needs a
# data weight ~3× stronger than α = 1 (fitted for α = 2/3 on the same frames; 12.5 and 75 °/s).
KF_HYPER_LAPLACIAN = (30.0, 0.006)
LAMBDA_RANGE = {"kf": (30.0, 300000.0), "wiener": (3.0, 30000.0)}
RANGE_PERCENTILES = (0.5, 99.5)


@dataclass(frozen=True)
class NoiseLambda:
    """The data weight for a frame of noise σ̂ (unit range): ``λ = scale / (σ̂ (1 + σ̂/knee))``,
    clamped to [lo, hi].

    ∝ 1/σ̂² (the MAP weight) for noisy frames, ∝ 1/σ̂ for quiet ones, where the measured optima
    flatten out (the prior, not the noise, then limits the restoration).
    """

    scale: float
    knee: float
    lo: float
    hi: float

    def __post_init__(self):
        ok = all(math.isfinite(v) for v in (self.scale, self.knee, self.lo, self.hi))
        if not (ok and self.scale > 0 and self.knee > 0 and 0 < self.lo <= self.hi):
            raise DeconvError(f"NoiseLambda: expected scale > 0, knee > 0 and 0 < lo ≤ hi, got {self}")

    @classmethod
    def default(cls, method: str, alpha: float = 1.0) -> NoiseLambda:
        """The shipped rule for `method` (and, for "kf", the prior exponent `alpha`)."""
        if method == "kf" and alpha < 1:
            return cls(*KF_HYPER_LAPLACIAN, *LAMBDA_RANGE[method])
        return cls(NOISE_LAMBDA[method], NOISE_KNEE, *LAMBDA_RANGE[method])

    def __call__(self, sigma):
        """λ for σ̂ (a float, or an array of σ̂ → an array of λ)."""
        sigma = np.maximum(np.asarray(sigma, dtype=np.float64), 1e-9)
        lam = np.clip(self.scale / (sigma * (1 + sigma / self.knee)), self.lo, self.hi)
        return float(lam) if lam.ndim == 0 else lam


def value_range_of(img, value_range) -> tuple[float, float]:
    if value_range is None:
        return robust_range(img)
    try:
        lo, hi = (float(v) for v in value_range)
    except (TypeError, ValueError):
        raise DeconvError(f"value_range: expected (lo, hi) counts, got {value_range!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise DeconvError(f"value_range: expected finite lo < hi, got {(lo, hi)}")
    return lo, hi


def robust_range(image: np.ndarray) -> tuple[float, float]:
    """(lo, hi) counts mapped to 0 and 1 internally: the 0.5/99.5 percentiles of a subsample of at
    most 40 000 pixels (a regular grid: at 640×480 every 3rd row and column)."""
    step = max(1, math.ceil(math.sqrt(image.size / 40000)))
    sub = np.asarray(image[::step, ::step], dtype=np.float32)
    lo, hi = np.percentile(sub, RANGE_PERCENTILES)
    lo, hi = float(lo), float(hi)
    if not hi - lo > 1e-6 * max(1.0, abs(lo)):  # flat frame: any scale works, keep counts
        hi = lo + 1.0
    return lo, hi


@njit(cache=True, nogil=True)
def _immerkaer_sum(img, row_step):
    """Σ |img ⊛ [[1,−2,1],[−2,4,−2],[1,−2,1]]| over interior pixels of every `row_step`-th row."""
    h, w = img.shape
    acc = 0.0
    n = 0
    for i in range(1, h - 1, row_step):
        up, mid, dn = img[i - 1], img[i], img[i + 1]
        for j in range(1, w - 1):
            corners = (np.float32(up[j - 1]) + np.float32(up[j + 1])
                       + np.float32(dn[j - 1]) + np.float32(dn[j + 1]))
            edges = np.float32(up[j]) + np.float32(dn[j]) + np.float32(mid[j - 1]) + np.float32(mid[j + 1])
            acc += abs(corners - 2 * edges + 4 * np.float32(mid[j]))
            n += 1
    return acc, n


def noise_sigma(image: np.ndarray, value_range: tuple[float, float] | None = None) -> float:
    """Temporal-noise RMS of a frame in unit range (Immerkær 1996, "Fast noise variance estimation").

    The Laplacian-difference mask cancels smooth structure; blur removes most of the rest, so on a
    blurry frame this is close to the sensor noise (NETD) over the frame's robust range.
    """
    img = check_image(image)
    lo, hi = robust_range(img) if value_range is None else value_range
    if min(img.shape) < 3:
        return 0.0
    acc, n = _immerkaer_sum(img, max(1, img.shape[0] // 64))   # ~64 rows: plenty of samples
    return float(math.sqrt(math.pi / 2) / 6 * acc / max(n, 1) / (hi - lo))
