"""The camera's rotation from a live stream of frames: a gyro for a payload that has none.

Each frame is registered against the one before it (`thermod.motion.picture.PairRegistrar`, working
images shrunk before they are normalised). The rotation φ_k between frames k−1 and k gives the mean
rate ω_k = φ_k / (t_k − t_{k−1}) at the interval's midpoint, lagged by what the detector does to the
picture: a smeared frame is registered at its exponential's centroid, τ before its read time (Eq. 11),
and its rows a mean share of the readout before that (`PairFit.lead`), so ω_k stands at
m_k = ½(t_{k−1} + t_k) − τ − lead · readout.

Samples at `rate_hz` are the rates interpolated linearly between consecutive midpoints and held
beyond the newest one. Frame k arrives with ω_k, so the samples up to t_{k−1} (plus `LEAD_SAMPLES`)
go out then: a frame is deblurred one frame period later than with a gyro, never with a rate
extrapolated over more than (t_{k−1} − m_k)⁺ = (τ + lead · readout − ½ period)⁺.

The rule it keeps: a rate only where the pictures measured it (by corners, else by every pixel), or
across one interval between two measured ones (a pair that cannot be registered: a cut, a blank frame),
which is bridged by its neighbours' rates with σ widened by half their difference. Two unknown
intervals in a row, or one over `GAP_PERIODS` frame intervals (frames lost, a camera stalled), stop
the samples; the next say `gap_before`, and the frames whose kernel window spans the hole pass
through. A repeated frame is skipped and the next registered across it. A static
overlay (a logo, OSD text) is found as the import finds it (`thermod.motion.track.overlay_mask`), on
running means over the stream (`OverlayWatch`), and no corner is taken on it.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from thermod.motion.picture import U8_PER_UNIT, PairRegistrar
from thermod.motion.track import (
    DUPLICATE_ABS,
    GAP_PERIODS,
    MIN_REGISTERED_NCC,
    OVERLAY_MOVING_RATIO,
    gradient_magnitude,
    overlay_mask,
    registered_ncc,
    scene_motion,
)
from thermod.physics.geometry import Intrinsics

LEAD_SAMPLES = 3          # samples sent past the frame time (the kernel window's padding)
MAX_REPEATS = 2           # repeated frames skipped in a row; then the pair is registered anyway (a still,
                          # noiseless scene repeats without a camera fault)
MAX_BRIDGED = 1           # unknown intervals between two measured ones that their rates are interpolated over
INTERVALS = 31            # frame intervals the gap rule's median period is taken over
MIN_INTERVALS = 5         # ... and how many it needs first
DEFAULT_RATE_HZ = 1000.0
# corners and pyramid levels per pair: 100 and 2 (a working frame moves a few px per period) against the
# import's 150 and 3 took 4.7 ms a frame for 7.3 at 640×480, with the rate error 5.5 °/s RMS for 5.2
# (the simulated payload's loop, 44 °/s RMS)
FEATURES = 100
LK_LEVELS = 2
# the tracking window, px: 11 against 15 took 4.8–5.2 ms a frame for 7.6–8.7, the rate error 8.20 °/s RMS
# for 8.39, with 3.8 % of pairs left to the dense fit for 2.0 % (400 frames of the payload's loop)
LK_WINDOW = 11
OVERLAY_MEMORY = 0.98     # the overlay's running means keep this much per pair (~50 pairs, 1 s at 50 fps)
OVERLAY_EVERY = 5         # pairs between two looks for an overlay (the first after as many)


class OverlayWatch:
    """A static overlay in a stream of working images: running means of each pixel's gradient and
    frame-to-frame change, judged every `OVERLAY_EVERY` pairs by the import's rule (`overlay_mask`).
    While the scene does not move (a still camera) the last judgement stands: nothing tells an
    overlay from the scene then, and corners on either agree."""

    def __init__(self):
        self._G: np.ndarray | None = None
        self._D: np.ndarray | None = None
        self._pairs = 0
        self.mask: np.ndarray | None = None

    def add(self, prev: np.ndarray, cur: np.ndarray) -> None:
        z0, z1 = prev.astype(np.float32), cur.astype(np.float32)
        g, d = gradient_magnitude(z1), np.abs(z1 - z0)
        if self._G is None or self._G.shape != g.shape:
            self._G, self._D, self._pairs = g, d, 0
        else:
            self._G = OVERLAY_MEMORY * self._G + (1 - OVERLAY_MEMORY) * g
            self._D = OVERLAY_MEMORY * self._D + (1 - OVERLAY_MEMORY) * d
        self._pairs += 1
        if self._pairs % OVERLAY_EVERY == 0:
            moving = scene_motion(self._G, self._D)
            if moving is not None and moving >= OVERLAY_MOVING_RATIO:
                self.mask = overlay_mask(self._G, self._D)

    @property
    def fraction(self) -> float:
        return float(self.mask.mean()) if self.mask is not None else 0.0


@dataclass
class Samples:
    """Rate samples from the pictures: host times `t` [n], camera-frame `rate` [n, 3] rad/s, `sigma` [n]
    rad/s (1σ per axis); `gap_before`: the motion between the last samples and these is unknown."""

    t: np.ndarray
    rate: np.ndarray
    sigma: np.ndarray
    gap_before: bool = False


class LiveTrack:
    """Streaming rotation track (module docstring). `push(frame, t)` per frame, in read order; it returns
    the new `Samples` (or None) and keeps counters in `counts`."""

    def __init__(self, intrinsics: Intrinsics, *, tau_s: float, readout_s: float = 0.0,
                 rate_hz: float = DEFAULT_RATE_HZ, work_width: int = 160):
        if not (tau_s >= 0 and readout_s >= 0 and rate_hz > 0):
            raise ValueError(f"tau_s, readout_s ≥ 0 and rate_hz > 0 expected, got {tau_s}, {readout_s}, "
                             f"{rate_hz}")
        self.reg = PairRegistrar(intrinsics, work_width=work_width, resize_first=True, max_features=FEATURES,
                                 lk_levels=LK_LEVELS, lk_window=LK_WINDOW)
        self.tau_s, self.readout_s, self.h = float(tau_s), float(readout_s), 1.0 / float(rate_hz)
        self._prev: np.ndarray | None = None
        self._prev_t = -math.inf
        self._anchor: tuple[float, np.ndarray, float] | None = None   # (m, ω, σ) of the newest interval
        self._next_t: float | None = None    # the next sample's time (None: a new stretch starts)
        self._gap = False
        self._repeats = 0
        self._unknown = 0                    # unknown intervals since the anchor's
        self._last_t = -math.inf             # the newest frame's time, repeated or not
        self._intervals: collections.deque[float] = collections.deque(maxlen=INTERVALS)
        self.counts = {"frames": 0, "measured": 0, "dense": 0, "untracked": 0, "cut": 0, "duplicate": 0,
                       "bridged": 0, "gap": 0, "samples": 0}
        self.overlay = OverlayWatch()
        self.last_sigma_rad_s = math.nan

    def push(self, frame, t: float) -> Samples | None:
        """Register the frame read at host time `t` (its last row) against the previous one."""
        return self.push_working(self.prepare(frame), t)

    def prepare(self, frame) -> np.ndarray:
        """The frame's working image, the overlay found so far left out of its normalisation (its
        strokes, the brightest pixels, would set the 99 % level and flatten the scene)."""
        return self.reg.prepare(frame, self.overlay.mask)

    def push_working(self, cur: np.ndarray, t: float) -> Samples | None:
        """`push` of a frame already turned into its working image (`prepare`)."""
        t = float(t)
        self.counts["frames"] += 1
        if t > self._last_t > -math.inf:
            self._intervals.append(t - self._last_t)
        self._last_t = max(self._last_t, t)
        prev, t_prev = self._prev, self._prev_t
        if prev is not None and self._repeats < MAX_REPEATS and \
                np.median(np.abs(cur.astype(np.int16) - prev)) <= DUPLICATE_ABS * U8_PER_UNIT:
            self.counts["duplicate"] += 1          # a repeated frame: register the next one across it
            self._repeats += 1
            return None
        self._repeats = 0
        self._prev, self._prev_t = cur, t
        if prev is None or not t > t_prev:
            return None
        period = float(np.median(self._intervals)) if len(self._intervals) >= MIN_INTERVALS else math.inf
        if t - t_prev > GAP_PERIODS * period:
            self.counts["gap"] += 1     # only the net rotation across it was seen: a hole, not a guess
            self._lose_stretch()
            return None
        self.overlay.add(prev, cur)
        overlay = self.overlay.mask
        predicted = self._anchor[1] * (t - t_prev) if self._anchor is not None else None
        fit = self.reg.measure(prev, cur, bands=False, predicted=predicted, exclude=overlay)
        if fit is None:                # too few corners agree: every pixel, rather than a bridge's wait
            fit = self.reg.measure_dense(prev, cur, predicted=predicted, exclude=overlay)
            self.counts["dense"] += fit is not None
        status = "untracked" if fit is None else "ok"
        if fit is not None and not registered_ncc(prev.astype(np.float32), cur.astype(np.float32), fit.rotvec,
                                                  self.reg.work, overlay) >= MIN_REGISTERED_NCC:
            status = "cut"
        if status != "ok":
            self.counts[status] += 1
            self._unknown += 1
            if self._anchor is None or self._unknown > MAX_BRIDGED:
                self._lose_stretch()
            return None
        self.counts["measured"] += 1
        bridged, self._unknown = self._unknown > 0, 0
        self.counts["bridged"] += bridged
        dt = t - t_prev
        rate = fit.rotvec / dt
        sigma = fit.noise_rad / dt
        self.last_sigma_rad_s = sigma
        lag = self.tau_s + fit.lead * self.readout_s
        old, self._anchor = self._anchor, (0.5 * (t_prev + t) - lag, rate, sigma)
        if self._next_t is None:                 # a stretch starts where its first interval does
            self._next_t = t_prev - lag
        # across a bridged interval the rate may have done anything between its neighbours' values
        spread = 0.5 * float(np.linalg.norm(rate - old[1])) if bridged and old is not None else 0.0
        return self._emit(old, t_prev + LEAD_SAMPLES * self.h, spread)

    def _lose_stretch(self) -> None:
        """The motion over the last intervals is unknown: the samples stop, and resume flagged."""
        if self._next_t is not None:
            self._gap = True
        self._anchor, self._next_t, self._unknown = None, None, 0

    def _emit(self, old, until: float, spread: float = 0.0) -> Samples | None:
        n = int(math.floor((until - self._next_t) / self.h)) + 1
        if n <= 0:
            return None
        ts = self._next_t + self.h * np.arange(n)
        m, rate, sigma = self._anchor
        if old is None:
            w = np.tile(rate, (n, 1))
            s = np.full(n, sigma)
        else:
            m0, r0, s0 = old
            f = np.clip((ts - m0) / (m - m0), 0.0, 1.0)[:, None] if m > m0 else np.ones((n, 1))
            w = r0 + f * (rate - r0)
            s = np.where(f[:, 0] < 1.0, np.maximum(s0, sigma) + spread, sigma)
        self._next_t = float(ts[-1] + self.h)
        gap, self._gap = self._gap, False
        self.counts["samples"] += n
        return Samples(ts, w.astype(np.float32), s.astype(np.float32), gap)


__all__ = ["DEFAULT_RATE_HZ", "LEAD_SAMPLES", "LiveTrack", "Samples"]
