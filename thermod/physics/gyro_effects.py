"""Gyro-side corrections of raw samples that `Calibration.condition_gyro` applies before the linear
gyro → camera map: the continuation of clipped runs and the inverse of the chip's digital low-pass.

Both work on raw samples (gyro frame, rad/s, bias included) at a near-constant output data rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# The inverse low-pass is rolled off above REG_FACTOR × f_c (order 2·REG_ORDER): 1/H grows as f², so
# without it the white noise above the cutoff would be amplified without bound. At f_c the roll-off
# costs 0.14 %, at 3 f_c half the amplitude.
REG_FACTOR = 3.0
REG_ORDER = 3
# A sample counts as clipped when |rate| ≥ range·(1 − CLIP_TOL): float32 storage and an LSB
# quantisation after the clip put it a few 1e-5 below the range.
CLIP_TOL = 1e-4
# Samples each side of a clipped run that its continuation's edge value and slope are fitted to (15 ms
# at 1 kHz: long enough to average a 1 °/s quantisation, short enough for the curve to be a quadratic).
EDGE_SAMPLES = 15


def butterworth2(f_hz, cutoff_hz: float) -> np.ndarray:
    """H(j2πf) of the 2nd-order Butterworth low-pass, H(s) = ω_c² / (s² + √2 ω_c s + ω_c²).

    Its group delay at DC is √2 / (2π f_c) (e.g. 9 ms at 25 Hz): what a time offset absorbs; the
    attenuation |H| = 1/√(1 + (f/f_c)⁴) is what tells the two apart.
    """
    x = np.asarray(f_hz, np.float64) / cutoff_hz
    return 1.0 / (1.0 - x * x + 1j * math.sqrt(2.0) * x)


def group_delay_s(cutoff_hz: float) -> float:
    """DC group delay of `butterworth2`: √2 / (2π f_c)."""
    return math.sqrt(2.0) / (2.0 * math.pi * cutoff_hz)


def inverse_lowpass(t: np.ndarray, rate: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """The rate before a 2nd-order Butterworth at `cutoff_hz`: ŵ = F⁻¹[R(f) / H(f) · F[w]].

    R(f) = 1 / (1 + (f / (REG_FACTOR f_c))^(2·REG_ORDER)) regularises the inverse above the cutoff.
    The series is extended at both ends by odd reflection (value and slope continue) before the FFT,
    so the ends of a short window are not wrapped onto each other. Sampling is taken as uniform at
    the median interval (MEMS output data rates are).
    """
    r = np.asarray(rate, np.float64)
    n = len(r)
    if n < 4:
        return r.copy()
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        return r.copy()
    m = min(n - 1, max(8, int(math.ceil(4.0 / (cutoff_hz * dt)))))
    head = 2.0 * r[:1] - r[m:0:-1]
    tail = 2.0 * r[-1:] - r[-2:-m - 2:-1]
    x = np.concatenate([head, r, tail])
    f = np.fft.rfftfreq(len(x), dt)
    g = 1.0 / butterworth2(f, cutoff_hz) / (1.0 + (f / (REG_FACTOR * cutoff_hz)) ** (2 * REG_ORDER))
    y = np.fft.irfft(np.fft.rfft(x, axis=0) * g[:, None], n=len(x), axis=0)
    return y[m:m + n]


def clipped_runs(rate_axis: np.ndarray, range_rad_s: float) -> list[tuple[int, int, float]]:
    """Runs (first, last, sign) of consecutive samples pinned at ±range on one axis."""
    a = np.asarray(rate_axis, np.float64)
    lim = range_rad_s * (1.0 - CLIP_TOL)
    runs = []
    for sign in (1.0, -1.0):
        m = np.r_[False, sign * a >= lim, False]
        d = np.diff(m.astype(np.int8))
        runs += [(int(i), int(j) - 1, sign) for i, j in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1),
                                                             strict=True)]
    return sorted(runs)


def _edge(t: np.ndarray, y: np.ndarray, idx: np.ndarray) -> tuple[float, float]:
    """Value and slope at t[idx[0]] of a quadratic least-squares fit over the samples `idx` (idx[0] next
    to the run)."""
    tt = t[idx] - t[idx[0]]
    c = np.polyfit(tt, y[idx], 2 if len(idx) >= 6 else 1)
    return float(np.polyval(c, 0.0)), float(np.polyval(np.polyder(c), 0.0))


def _side(y: np.ndarray, start: int, step: int, lim: float) -> np.ndarray:
    """Up to EDGE_SAMPLES unclipped sample indices from `start` outwards (stopping at a clipped one)."""
    idx = []
    i = start
    while 0 <= i < len(y) and len(idx) < EDGE_SAMPLES and abs(y[i]) < lim:
        idx.append(i)
        i += step
    return np.asarray(idx, int)


@dataclass(frozen=True)
class Continuation:
    """A clipped run [i0, i1] on one axis and the excess over the range it is continued with at gain 1
    (≥ 0, rad/s); `two_sided`: the signal is known on both sides of it."""

    axis: int
    i0: int
    i1: int
    sign: float
    excess: np.ndarray
    two_sided: bool


def continuations(t: np.ndarray, rate: np.ndarray, range_rad_s: float) -> list[Continuation]:
    """Every clipped run of `rate` (axis by axis, in time order) with the shape it is continued with.

    Between the last unclipped sample before a run and the first after it, the cubic Hermite with the
    value and slope the signal had on both sides is the natural continuation of a peak that the range
    cut off (a parabola with the steeper side's slope when the cubic stays below the range: the peak
    did go above it). Each side's value and slope come from a quadratic fit over up to EDGE_SAMPLES
    samples: a one-sample difference of a log quantised to 1 °/s is 0 or ±17.5 rad/s² at 1 kHz. A
    run with fewer than 4 unclipped samples on one side (at an end of the series) is continued as the
    known side's line, rising away from it. Runs with neither side known are left out.
    """
    t = np.asarray(t, np.float64)
    r = np.asarray(rate, np.float64)
    lim = range_rad_s * (1.0 - CLIP_TOL)
    out = []
    for a in range(r.shape[1]):
        y = r[:, a]
        for i0, i1, sign in clipped_runs(y, range_rad_s):
            before, after = _side(y, i0 - 1, -1, lim), _side(y, i1 + 1, 1, lim)
            tr = t[i0:i1 + 1]
            if len(before) >= 4 and len(after) >= 4:
                ta, tb = t[i0 - 1], t[i1 + 1]
                ya, sa = _edge(t, y, before)
                yb, sb = _edge(t, y, after)
                h = tb - ta
                u = (tr - ta) / h
                curve = ((2 * u**3 - 3 * u**2 + 1) * ya + (u**3 - 2 * u**2 + u) * h * sa
                         + (-2 * u**3 + 3 * u**2) * yb + (u**3 - u**2) * h * sb)
                excess = np.maximum(sign * curve - range_rad_s, 0.0)
                if not excess.any():
                    excess = max(abs(sa), abs(sb)) * h * u * (1.0 - u)
                out.append(Continuation(a, i0, i1, sign, excess, True))
            elif len(before) >= 4 or len(after) >= 4:
                edge, side = (i0 - 1, before) if len(before) >= 4 else (i1 + 1, after)
                y0, slope = _edge(t, y, side)
                excess = np.maximum(sign * (y0 + slope * (tr - t[edge])) - range_rad_s, 0.0)
                if not excess.any():
                    excess = abs(slope) * np.abs(tr - t[edge])
                out.append(Continuation(a, i0, i1, sign, excess, False))
    return out


def unclip(t: np.ndarray, rate: np.ndarray, range_rad_s: float, gain: float = 1.0,
           run_gains: tuple = ()) -> np.ndarray:
    """Clipped runs replaced by their continuation above the range (`continuations`), its excess over
    the range scaled by `gain` (fitted from the images: the shape of the cut peak is only guessed).

    `run_gains`: one gain per run of `continuations(t, rate, range_rad_s)` instead, for one recording's
    whole series (what the discrepancy fit makes when one gain does not fit every run). Without them
    only runs known on both sides are continued: one side's line alone overshoots a long run many
    times (it was 7.6° for 1.0° on the real log from 30 s).
    """
    out = np.array(rate, np.float64, copy=True)
    runs = continuations(t, out, range_rad_s)
    if run_gains and len(run_gains) != len(runs):
        raise ValueError(f"unclip: {len(run_gains)} run gains for {len(runs)} clipped runs")
    for k, c in enumerate(runs):
        if not run_gains and not c.two_sided:
            continue
        g = run_gains[k] if run_gains else gain
        out[c.i0:c.i1 + 1, c.axis] = c.sign * (range_rad_s + g * c.excess)
    return out


def detect_clip_level(rate: np.ndarray, min_samples: int = 3) -> float:
    """The range a gyro clipped at: the largest |rate| of all axes, when ≥ `min_samples` samples sit on
    it exactly (a pile-up at the extreme of the distribution), or 0 when there is none.

    A MEMS gyro has one full-scale range for its three axes, so a level below another axis's peak is
    no range: a log quantised to 1 °/s piles samples up at each axis's own peak (15 °/s on an axis
    that barely turns, while another turns at 130 °/s), which would otherwise "clip" the busy axis.
    """
    r = np.abs(np.asarray(rate, np.float64))
    if r.ndim != 2 or r.size == 0:
        return 0.0
    top = float(r.max(initial=0.0))
    if not top > 0:
        return 0.0
    at = int(np.sum(r >= top * (1.0 - CLIP_TOL)))
    return top if at >= min_samples else 0.0
