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


# ---------------------------------------------------------------- a stack of tiles (one call each)
@njit(cache=True, nogil=True, fastmath=True)
def xstep_stack(kty, k2, g2, d, c, norm, out):
    """`xstep` on every tile of a stack (n, hp, wp // 2 + 1), all sharing one |F∇|²."""
    for t in range(kty.shape[0]):
        xstep(kty[t], k2[t], g2, d[t], c, norm, out[t])


@njit(cache=True, nogil=True)
def wiener_stack(kty, k2, g2, c, norm, out):
    for t in range(kty.shape[0]):
        wiener_solve(kty[t], k2[t], g2, c, norm, out[t])


@njit(cache=True, nogil=True)
def scatter_psfs(weights, origins, out):
    """Each tile's kernel (weights[t] zero-padded to a common size) circularly shifted so that its
    origin sits at (0, 0) of out[t]; a kernel larger than the tile wraps onto itself (aliasing)."""
    n, hp, wp = out.shape
    for t in range(n):
        out[t] = 0.0
        oy, ox = origins[t, 0], origins[t, 1]
        for i in range(weights.shape[1]):
            for j in range(weights.shape[2]):
                v = weights[t, i, j]
                if v != 0:
                    out[t, (i - oy) % hp, (j - ox) % wp] += v


@njit(cache=True, nogil=True)
def otf_stack(f, K, K2):
    """K = F(psf), K2 = |K|² of every tile."""
    n, h, w = f.shape
    for t in range(n):
        for i in range(h):
            for j in range(w):
                v = f[t, i, j]
                K[t, i, j] = v
                K2[t, i, j] = v.real * v.real + v.imag * v.imag


@njit(cache=True, nogil=True)
def prepare_stack(img, boxes, lo, scale, out):
    """`prepare` each tile's box (y0, y1, x0, x1) of img into out[t]."""
    for t in range(boxes.shape[0]):
        y0, y1, x0, x1 = boxes[t, 0], boxes[t, 1], boxes[t, 2], boxes[t, 3]
        prepare(img, y0, x0, y1 - y0, x1 - x0, lo, scale, out[t])


@njit(cache=True, nogil=True)
def conj_mul_stack(k, y, out):
    for t in range(k.shape[0]):
        conj_mul(k[t], y[t], out[t])


@njit(cache=True, nogil=True)
def blend_stack(x, boxes, supports, rows, cols, wys, wxs, lo, rng, out):
    """out[support] += (x·rng + lo)·w_y·w_x for every tile: its solution in counts, weighted by its
    share of the partition of unity. Tile t is grid cell (rows[t], cols[t]); its support
    (ys, ye, xs, xe) lies inside its box (y0, y1, x0, x1); wys[r] / wxs[c] hold the weights from
    the support's start."""
    for t in range(x.shape[0]):
        y0, x0 = boxes[t, 0], boxes[t, 2]
        ys, ye, xs, xe = supports[t, 0], supports[t, 1], supports[t, 2], supports[t, 3]
        wy = wys[rows[t]]
        wx = wxs[cols[t]]
        for i in range(ye - ys):
            for j in range(xe - xs):
                v = x[t, ys - y0 + i, xs - x0 + j] * rng + lo
                out[ys + i, xs + j] += v * wy[i] * wx[j]
