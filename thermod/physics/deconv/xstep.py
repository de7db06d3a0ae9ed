"""K&F x-step and the Wiener solve in the Fourier domain, plus the unit scaling and periodic
boundary extension around them (numba passes over plan-owned buffers).

x-step: ``X = (K̄·Y + (β/λ) F(∇ᵀw)) / (|K|² + (β/λ)(|F∂x|² + |F∂y|²))``; Wiener fast path:
``X = K̄Y / (|K|² + (1/λ)|F∇|²)``.

Boundaries: the unit-scaled frame is extended to the FFT size by a replicate-then-taper periodic
extension (each padded row/column blends the near edge into the opposite edge with a raised
cosine, zero slope at both joins), so circular convolution sees no jump and no ringing frame
appears at the borders.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, fastmath=True)
def xstep(kty, k2, g2, d, c, norm, out):
    """out = norm·(K̄Y + c·D) / (|K|² + c·|G|²) on the half spectrum, c = β/λ (norm: FFTW's 1/N)."""
    h, w = kty.shape
    for i in range(h):
        for j in range(w):
            r = norm / (k2[i, j] + c * g2[i, j])   # real denominator: no complex division
            out[i, j] = (kty[i, j] + c * d[i, j]) * r


@njit(cache=True, nogil=True)
def conj_mul(k, y, out):
    h, w = k.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = k[i, j].conjugate() * y[i, j]


@njit(cache=True, nogil=True)
def wiener_solve(kty, k2, g2, c, norm, out):
    h, w = kty.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = norm * kty[i, j] / (k2[i, j] + c * g2[i, j])


@njit(cache=True, nogil=True)
def prepare(img, y0, x0, hh, ww, lo, scale, out):
    """Unit-scale img[y0:y0+hh, x0:x0+ww] into out[:hh, :ww] and fill the rest of `out` with a
    periodic extension: replicate the edge, raised-cosine blend into the opposite edge."""
    hp, wp = out.shape
    for i in range(hh):
        for j in range(ww):
            out[i, j] = (np.float32(img[y0 + i, x0 + j]) - lo) * scale
    gx = wp - ww
    if gx > 0:
        for j in range(gx):
            c = np.float32(0.5 - 0.5 * math.cos(math.pi * (j + 1) / (gx + 1)))
            for i in range(hh):
                out[i, ww + j] = (1 - c) * out[i, ww - 1] + c * out[i, 0]
    gy = hp - hh
    if gy > 0:
        for i in range(gy):
            c = np.float32(0.5 - 0.5 * math.cos(math.pi * (i + 1) / (gy + 1)))
            for j in range(wp):
                out[hh + i, j] = (1 - c) * out[hh - 1, j] + c * out[0, j]


@njit(cache=True, nogil=True)
def finish(x, hh, ww, lo, rng, out):
    for i in range(hh):
        for j in range(ww):
            out[i, j] = x[i, j] * rng + lo
