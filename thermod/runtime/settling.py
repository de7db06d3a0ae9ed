"""Whether the stream has reached its steady latency since it started (health's ``warming_up``).

The first seconds of a stream run slower than the rest: the FFT plans of grid shapes the warm-up did
not build, the governor's first in-stream costs, page faults of fresh buffers, a cold disk cache.
The stream is *warming up* until two consecutive `WINDOW_S` windows of published frames agree on
their 95th-percentile latency within `TOLERANCE` (each with at least `MIN_FRAMES` frames); then it
is steady, for good. A stream that has not settled after `GIVE_UP_S` is reported as not warming
up but unsettled (``steady_after_s`` stays None): its latency moves for another reason (load).
"""

from __future__ import annotations

import threading

import numpy as np

WINDOW_S = 5.0
TOLERANCE = 0.2
MIN_FRAMES = 20
GIVE_UP_S = 60.0


class Settling:
    """Fed each published frame's latency; says whether the stream is still warming up."""

    def __init__(self, start: float) -> None:
        self.start = float(start)
        self.steady_after_s: float | None = None
        self._window: list[float] = []
        self._window_end = self.start + WINDOW_S
        self._previous_p95: float | None = None
        self._lock = threading.Lock()

    def add(self, now: float, latency_s: float) -> None:
        with self._lock:
            if self.steady_after_s is not None:
                return
            while now >= self._window_end:
                self._close(self._window_end)
                self._window_end += WINDOW_S
            self._window.append(float(latency_s))

    def _close(self, end: float) -> None:
        if len(self._window) < MIN_FRAMES:
            self._previous_p95 = None
        else:
            p95 = float(np.percentile(self._window, 95))
            prev = self._previous_p95
            if prev is not None and abs(p95 - prev) <= TOLERANCE * max(p95, prev):
                self.steady_after_s = round(end - self.start, 1)
            self._previous_p95 = p95
        self._window = []

    def state(self, now: float) -> dict:
        with self._lock:
            steady = self.steady_after_s
        return {"warming_up": steady is None and now - self.start < GIVE_UP_S, "steady_after_s": steady}
