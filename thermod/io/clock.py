"""Device-clock → host-clock mapping (docs/design.md §2: "counter × period + offset, fitted on the earliest
arrivals, drift-tracked").

A device (gyro FIFO, serial IMU, GigE camera) numbers its samples with a counter that runs on its own
oscillator. The host sees each counter value only when a read returns, i.e. *after* the sample was
taken, by a transport delay that is never negative (bus transfer, scheduling, USB polling, a
preempted thread). So every observation lies on or above the true line

    host(ticks) = offset + (1 + drift) · ticks · nominal_period

and the best estimate of that line is the one that touches the observations from below: the lower
convex hull of the recent (ticks, arrival) points, taking the hull edge that spans their mean tick
(the supporting line that minimises the mean distance to the points; Moon, Skelly & Towsley 1999).
Late reads never pull the fit up, however late they are; they cost nothing but their own sample.

Cheap enough for a 1 kHz source read every few ms: observations are reduced to per-bucket minima
(relative to the current line) and the hull is refitted only when a bucket closes.

Jumps: a device counter that goes backwards (device reset, reconnect) or an arrival that comes
earlier than the line allows (host clock stepped back, counter jumped ahead) restarts the fit at
once; arrivals that stay far later than the line for `confirm_s` (host clock stepped forward) do so
after confirmation. The drift estimate survives a restart, as it belongs to the oscillator.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from thermod.errors import DeviceError


class ClockMapper:
    """Map device sample counters to host CLOCK_MONOTONIC seconds.

    Parameters
    ----------
    nominal_period_s
        Seconds per device tick by the datasheet (1e-3 for a 1 kHz sample counter, 1e-9 for a
        nanosecond timestamp).
    window_s
        Sliding fit window in device seconds; long enough to average the transport jitter, short
        enough to follow the oscillator's thermal drift.
    bucket_s
        Observations are reduced to one earliest-arrival point per bucket of this many device
        seconds (default ``min(0.1, window_s / 64)``).
    min_span_s
        Below this span of observations only the offset is fitted (slope = last drift estimate).
    early_s
        An arrival earlier than the line by more than this is impossible under a delay-only model:
        the clock relation changed, so the fit restarts.
    late_s, confirm_s
        Arrivals all later than the line by more than ``late_s`` for ``confirm_s`` host seconds
        mean the host clock stepped forward (a single late read is normal and ignored).
    max_drift_ppm
        Largest oscillator error expected; until the drift is fitted, an early arrival within what
        this drift allows lowers the line instead of restarting it.
    name
        Device name used in error messages.

    Attributes
    ----------
    drift_ppm : float
        Host seconds per nominal device second, minus one, in ppm (positive: device runs slow).
    residual_std_s : float
        Standard deviation of the per-bucket earliest arrivals about the fitted line: how tightly
        the lower envelope is defined (0 until a line has been fitted).
    resets : int
        Number of detected jumps (counter reset, host clock step) after which the fit restarted.
    """

    def __init__(self, nominal_period_s: float, window_s: float = 20.0, *, bucket_s: float | None = None,
                 min_span_s: float = 0.5, early_s: float = 0.002, late_s: float = 0.02,
                 confirm_s: float = 0.5, max_drift_ppm: float = 2000.0, name: str = "device clock"):
        if not (nominal_period_s > 0 and math.isfinite(nominal_period_s)):
            raise DeviceError(f"{name}: clock mapper nominal_period_s must be a positive number, "
                              f"got {nominal_period_s!r}")
        if not window_s > 0:
            raise DeviceError(f"{name}: clock mapper window_s must be > 0, got {window_s!r}")
        self.name = name
        self.period = float(nominal_period_s)
        self.window_s = float(window_s)
        self.bucket_s = float(bucket_s) if bucket_s else min(0.1, self.window_s / 64)
        self.min_span_s = float(min_span_s)
        self.early_s, self.late_s, self.confirm_s = float(early_s), float(late_s), float(confirm_s)
        self.max_drift = float(max_drift_ppm) * 1e-6
        self.resets = 0
        self.observations = 0
        self._slope = 0.0          # drift as a fraction; kept across restarts
        self._clear()

    # -- state ---------------------------------------------------------------------------------
    def _clear(self) -> None:
        self._ref: int | None = None      # tick origin, an exact int (GigE ns counters exceed 2**53)
        self._a = 0.0                     # host = ref_time + _a + (1 + _slope) · x
        self._last_x = -math.inf
        self._buckets: deque[list[float]] = deque()   # [bucket index, x, y] earliest arrival
        self._late: list[tuple[int, float]] = []       # pending evidence of a forward host step
        self._late_since = math.nan
        self._resid_std = 0.0
        self._fitted = False              # slope fitted since the last (re)start

    @property
    def ready(self) -> bool:
        """True once at least one observation has been made (to_host works)."""
        return self._ref is not None

    @property
    def drift_ppm(self) -> float:
        return self._slope * 1e6

    @property
    def residual_std_s(self) -> float:
        return self._resid_std

    # -- observations --------------------------------------------------------------------------
    def observe(self, device_ticks: int, host_arrival: float) -> bool:
        """Add one observation: a counter value and a host time known to be no earlier than it.

        For a FIFO, pass the counter of the newest sample read and the host time taken right after
        the read that counted it. Returns True when this observation caused a restart (jump).
        """
        ticks = int(device_ticks)
        t = float(host_arrival)
        if not math.isfinite(t):
            raise DeviceError(f"{self.name}: host arrival time must be finite, got {host_arrival!r}")
        self.observations += 1
        if self._ref is None:
            self._start(ticks, t)
            return False
        x = (ticks - self._ref) * self.period
        y = t - x
        err = y - self._line(x)
        jump = False
        if x < self._last_x - 0.5 * self.period:
            jump = True                                  # counter went backwards: device reset
        elif err < -(self.early_s + (0.0 if self._fitted else self.max_drift * abs(x))):
            jump = True                                  # earlier than possible: clock relation changed
        elif err > self.late_s:
            if not self._late:
                self._late_since = t
            self._late.append((ticks, t))
            if t - self._late_since >= self.confirm_s and len(self._late) >= 3:
                pending = self._late
                self._restart(*pending[0])
                for k, tt in pending[1:]:
                    self._add(k, tt)
                return True
            return False
        else:
            self._late.clear()
        if jump:
            self._restart(ticks, t)
            return True
        self._add(ticks, t)
        return False

    def restart(self, anchor: tuple[int, float] | None = None) -> None:
        """Forget the offset (keep the drift): the driver knows the counter lost continuity, e.g. after
        a FIFO flush whose lost sample count is only estimated. Not counted in ``resets``.

        ``anchor`` (ticks, host time) starts the new fit at a point the driver knows, such as the
        flush itself: the first read after a FIFO overflow is often a late one (the reader was
        starved, which is why the FIFO overflowed), and a fit started on it times the samples
        after the gap late by that read's delay until a timely read lowers the line."""
        self._clear()
        if anchor is not None:
            self._start(int(anchor[0]), float(anchor[1]))

    def _start(self, ticks: int, t: float) -> None:
        self._ref = ticks
        self._a = t
        self._last_x = 0.0
        self._buckets.append([0.0, 0.0, t])

    def _restart(self, ticks: int, t: float) -> None:
        self.resets += 1
        self._clear()
        self._start(ticks, t)

    def _line(self, x: float) -> float:
        return self._a + self._slope * x

    def _add(self, ticks: int, t: float) -> None:
        x = (ticks - self._ref) * self.period
        y = t - x
        self._last_x = max(self._last_x, x)
        b = math.floor(x / self.bucket_s)
        last = self._buckets[-1]
        if b == last[0]:
            # keep the earliest arrival relative to the current line (drift within a bucket matters)
            if y - self._slope * x < last[2] - self._slope * last[1]:
                last[1], last[2] = x, y
            closed = False
        else:
            self._buckets.append([b, x, y])
            closed = True
        while self._buckets and self._buckets[0][1] < x - self.window_s:
            self._buckets.popleft()
        if closed or len(self._buckets) <= 2:
            self._fit()
        elif y < self._line(x):
            # a new earliest arrival inside the open bucket: lower the offset at once so the line
            # never predicts times later than an observed arrival
            self._a = y - self._slope * x

    def _fit(self) -> None:
        pts = self._buckets
        xs = [p[1] for p in pts]
        ys = [p[2] for p in pts]
        if xs[-1] - xs[0] < self.min_span_s:
            # too short to resolve the drift: keep the slope, touch the lowest point
            self._a = min(yy - self._slope * xx for xx, yy in zip(xs, ys, strict=True))
        else:
            hull = _lower_hull(xs, ys)
            xm = sum(xs) / len(xs)
            i = 0
            while i < len(hull) - 2 and xs[hull[i + 1]] <= xm:
                i += 1
            j, k = hull[i], hull[i + 1]
            slope = (ys[k] - ys[j]) / (xs[k] - xs[j])
            if abs(slope) <= self.max_drift:
                self._slope = slope
                self._a = ys[j] - slope * xs[j]
            else:
                # No oscillator drifts this much: a steadily growing backlog (an overloaded reader)
                # tilts the lower envelope. Keep the bounded slope and touch the lowest point.
                self._slope = float(np.clip(slope, -self.max_drift, self.max_drift))
                self._a = min(yy - self._slope * xx for xx, yy in zip(xs, ys, strict=True))
            self._fitted = True
        if len(xs) >= 3:
            r = np.asarray(ys) - (self._a + self._slope * np.asarray(xs))
            self._resid_std = float(r.std())

    # -- mapping -------------------------------------------------------------------------------
    def to_host(self, ticks):
        """Host CLOCK_MONOTONIC seconds of device counter value(s) ``ticks`` (int or int array)."""
        if self._ref is None:
            raise DeviceError(f"{self.name}: no clock observations yet, cannot map device ticks to host "
                              "time (call observe() after the first read)")
        if np.isscalar(ticks):
            x = (int(ticks) - self._ref) * self.period
            return self._a + (1.0 + self._slope) * x
        arr = np.asarray(ticks)
        if arr.dtype.kind in "iu":
            x = (arr.astype(np.int64) - np.int64(self._ref)).astype(np.float64) * self.period
        else:
            x = (arr.astype(np.float64) - float(self._ref)) * self.period
        return self._a + (1.0 + self._slope) * x

    def __repr__(self) -> str:
        return (f"ClockMapper({self.name!r}, period={self.period:g} s, drift={self.drift_ppm:+.1f} ppm, "
                f"resid={self.residual_std_s * 1e6:.1f} µs, resets={self.resets})")


def _lower_hull(xs: list[float], ys: list[float]) -> list[int]:
    """Indices of the lower convex hull of points sorted by x (Andrew's monotone chain)."""
    hull: list[int] = []
    for i in range(len(xs)):
        while len(hull) >= 2:
            o, a = hull[-2], hull[-1]
            cross = (xs[a] - xs[o]) * (ys[i] - ys[o]) - (ys[a] - ys[o]) * (xs[i] - xs[o])
            if cross <= 0:
                hull.pop()
            else:
                break
        hull.append(i)
    return hull
