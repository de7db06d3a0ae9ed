"""Preallocated, single-writer, timestamped ring buffers (gyro samples and camera frames).

Concurrency: exactly one thread writes a ring; any number read. Readers never block the writer.
Consistency uses a seqlock-style pair of counters instead of a lock:

- ``_head``    — number of items fully written (absolute index of the next slot);
- ``_claimed`` — ``_head`` plus the items the writer is currently writing.

The writer bumps ``_claimed`` *before* it touches any slot and ``_head`` *after* it is done. A
reader copies absolute range [a, b) with b ≤ ``_head`` and then checks that ``_claimed − capacity
≤ a``: if the writer has claimed (and so may have been overwriting) any of those slots in the
meantime, the copy is retried (or, for the oldest data, the range is trimmed). Python's GIL makes
the counter updates atomic and ordered with respect to the slot writes.

Times must increase within a ring. A sample stamped at or before the newest one (a host clock
jump, a re-synchronised device clock) starts a new *epoch*: older samples become unreadable, so a
kernel is never rendered across the discontinuity, and the jump is counted.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

_RETRIES = 8
REQUEST_EVERY_S = 0.002   # a waiting reader asks the gyro source for a read this often


@dataclass
class GyroWindow:
    """A consistent copy of the gyro samples in a time window (raw: gyro clock and frame)."""

    t: np.ndarray        # float64 [n]
    rate: np.ndarray     # float32 [n, 3]
    seq: np.ndarray      # int64 [n] device sample index
    gap: bool            # samples were lost inside (or just before the first sample of) the window
    newest_t: float      # newest sample time in the ring when read (nan if empty)
    oldest_t: float      # oldest readable sample time (nan if empty)

    def __len__(self) -> int:
        return len(self.t)


class GyroRing:
    """Ring of gyro samples: time (s, host monotonic), raw rate [3] (rad/s), device seq, gap flag.

    ``gap[i]`` means samples were lost just before sample i (FIFO overflow, dropped packet), or
    that it follows its predecessor by more than `max_step_s` (a hole in time the device counter
    did not show, e.g. a glitch of the clock mapping): a kernel must not interpolate across it.
    """

    def __init__(self, capacity: int, max_step_s: float | None = None):
        if capacity < 2:
            raise ValueError("capacity must be at least 2")
        self.capacity = int(capacity)
        self.max_step_s = max_step_s
        self._t = np.full(self.capacity, np.nan)
        self._rate = np.zeros((self.capacity, 3), np.float32)
        self._seq = np.zeros(self.capacity, np.int64)
        self._gap = np.zeros(self.capacity, bool)
        self._head = 0
        self._claimed = 0
        self._epoch_start = 0          # absolute index of the first sample readable in this epoch
        self._cond = threading.Condition()   # only for waiters; writes never take it for long
        self.clock_jumps = 0
        self.samples_written = 0
        self.gaps_marked = 0
        self.batches_rejected = 0
        self.time_holes = 0
        self.request = None            # the writer's source's ``request_read`` (see `wait_until`)

    # -------------------------------------------------------------------- writer
    def write(self, t: np.ndarray, rate: np.ndarray, seq0: int, gap_before: bool = False) -> int:
        """Append a batch (single writer). Returns the number of samples stored.

        Samples not strictly after the newest one start a new epoch (counted in `clock_jumps`).
        """
        t = np.asarray(t, np.float64).ravel()
        rate = np.asarray(rate, np.float32).reshape(-1, 3)
        n = len(t)
        if n == 0:
            return 0
        if len(rate) != n or not np.all(np.isfinite(t)):
            self.batches_rejected += 1
            raise ValueError(f"gyro batch: {n} times (all finite: {bool(np.all(np.isfinite(t)))}) vs "
                             f"{len(rate)} rates")
        if n > self.capacity:   # keep the newest; the dropped head of the batch is a gap
            t, rate = t[-self.capacity:], rate[-self.capacity:]
            seq0, gap_before = seq0 + n - self.capacity, True
            n = self.capacity
        jump = not np.all(np.diff(t) > 0)
        last = self._t[(self._head - 1) % self.capacity] if self._head > self._epoch_start else np.nan
        jump = jump or t[0] <= last
        if jump:
            # discontinuous time: history (and this batch up to its last backward step) is unusable
            back = np.flatnonzero(np.diff(t) <= 0)
            if len(back):
                k = back[-1] + 1
                t, rate, seq0, n = t[k:], rate[k:], seq0 + k, n - k
            self.clock_jumps += 1
            gap_before = True
            self._epoch_start = self._head
        h = self._head
        self._claimed = h + n
        idx = np.arange(h, h + n) % self.capacity
        self._t[idx] = t
        self._rate[idx] = rate
        self._seq[idx] = np.arange(seq0, seq0 + n)
        self._gap[idx] = False
        if gap_before:
            self._gap[idx[0]] = True
            self.gaps_marked += 1
        if self.max_step_s is not None:
            steps = np.diff(t, prepend=last if not jump else np.nan)
            holes = np.flatnonzero(steps > self.max_step_s)
            if len(holes):
                self._gap[idx[holes]] = True
                self.time_holes += len(holes)
        self._head = h + n
        self.samples_written += n
        with self._cond:
            self._cond.notify_all()
        return n

    # -------------------------------------------------------------------- readers
    def _bounds(self) -> tuple[int, int]:
        head = self._head
        return max(self._epoch_start, head - self.capacity, self._claimed - self.capacity), head

    def _search(self, lo: int, hi: int, tq: float) -> int:
        """First absolute index in [lo, hi) whose time is > tq (hi if none)."""
        c, tt = self.capacity, self._t
        while lo < hi:
            mid = (lo + hi) // 2
            if tt[mid % c] > tq:
                hi = mid
            else:
                lo = mid + 1
        return lo

    @property
    def newest_t(self) -> float:
        lo, hi = self._bounds()
        return float(self._t[(hi - 1) % self.capacity]) if hi > lo else float("nan")

    @property
    def count(self) -> int:
        return self._head

    def window(self, t0: float, t1: float, *, pad: int = 1) -> GyroWindow:
        """Samples with t0 < t ≤ t1, plus up to `pad` samples either side (for interpolation).

        `gap` is True when lost samples (or a hole in time) overlap (t0, t1].
        """
        for _ in range(_RETRIES):
            lo, hi = self._bounds()
            if hi <= lo:
                e = np.empty(0)
                return GyroWindow(e, np.empty((0, 3), np.float32), np.empty(0, np.int64), False,
                                  np.nan, np.nan)
            a = max(lo, self._search(lo, hi, t0) - pad)
            b = min(hi, self._search(a, hi, t1) + pad)
            idx = np.arange(a, min(b + 1, hi)) % self.capacity   # one extra to see a gap right after
            t, rate, seq, gap = self._t[idx], self._rate[idx], self._seq[idx], self._gap[idx]
            newest, oldest = self._t[(hi - 1) % self.capacity], self._t[lo % self.capacity]
            if self._claimed - self.capacity <= a and self._epoch_start <= a:
                # a gap flag on sample j marks a hole (t[j-1], t[j]); it matters if it overlaps (t0, t1]
                m = b - a
                tj, prev = t[: len(gap)], np.concatenate(([-np.inf], t[: len(gap) - 1]))
                has_gap = bool(np.any(gap & (tj > t0) & (prev < t1)))
                return GyroWindow(t[:m].copy(), rate[:m].copy(), seq[:m].copy(), has_gap,
                                  float(newest), float(oldest))
        raise RuntimeError("gyro ring: writer lapped the reader repeatedly (ring far too small)")

    def wait_until(self, t: float, timeout: float) -> bool:
        """Block until a sample at or after `t` is stored, or `timeout` s pass. True if covered.
        While it waits, `request` (the source's ``request_read``, if set) is called every
        `REQUEST_EVERY_S`: a FIFO driver then reads at once instead of at its next interval."""
        deadline = time.monotonic() + max(0.0, timeout)
        with self._cond:
            while not (self.newest_t >= t):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                if self.request is not None:
                    self.request()
                    left = min(left, REQUEST_EVERY_S)
                self._cond.wait(left)
        return True


@dataclass
class FrameSlot:
    """A consistent copy of one frame from the ring."""

    index: int           # absolute ring index (consecutive for every frame written)
    image: np.ndarray    # uint16 [H, W], owned by the caller
    t: float
    frame_id: int
    arrival: float
    gap_before: int
    ffc: bool = False    # the camera flagged a flat-field correction in progress


class FrameRing:
    """Ring of camera frames, preallocated uint16 [capacity, H, W]; read by absolute index.

    The scheduler consumes frames in order with `get(index, timeout)`; if it falls more than
    `capacity` frames behind, the overwritten frames are reported as lost (never silently).
    """

    def __init__(self, capacity: int, shape: tuple[int, int]):
        if capacity < 2:
            raise ValueError("capacity must be at least 2")
        self.capacity, self.shape = int(capacity), (int(shape[0]), int(shape[1]))
        self._img = np.zeros((self.capacity, *self.shape), np.uint16)
        self._t = np.zeros(self.capacity)
        self._arrival = np.zeros(self.capacity)
        self._fid = np.zeros(self.capacity, np.int64)
        self._gapb = np.zeros(self.capacity, np.int64)
        self._ffc = np.zeros(self.capacity, bool)
        self._head = 0
        self._claimed = 0
        self._cond = threading.Condition()
        self.frames_written = 0

    @property
    def head(self) -> int:
        """Absolute index of the next frame to be written (= frames written so far)."""
        return self._head

    def write(self, image: np.ndarray, t: float, frame_id: int, arrival: float, gap_before: int = 0,
              ffc: bool = False) -> int:
        """Copy one frame in (single writer); returns its absolute index. Wrong shape → ValueError."""
        if image.shape != self.shape:
            raise ValueError(f"frame shape {image.shape} does not match the ring's {self.shape}")
        h = self._head
        s = h % self.capacity
        self._claimed = h + 1
        np.copyto(self._img[s], image, casting="unsafe")
        self._t[s], self._arrival[s], self._fid[s], self._gapb[s] = t, arrival, frame_id, gap_before
        self._ffc[s] = bool(ffc)
        self._head = h + 1
        self.frames_written += 1
        with self._cond:
            self._cond.notify_all()
        return h

    def stamp(self, index: int) -> tuple[float, float] | None:
        """Frame `index`'s (t, arrival) without copying its image; None if not written yet or
        overwritten."""
        s = index % self.capacity
        if not (max(0, self._claimed - self.capacity) <= index < self._head):
            return None
        t, arrival = float(self._t[s]), float(self._arrival[s])
        return (t, arrival) if self._claimed - self.capacity <= index else None

    def get(self, index: int, timeout: float) -> FrameSlot | None | int:
        """Frame `index`: a `FrameSlot` copy; None if not yet written after `timeout` s; or, if it
        has already been overwritten, the (int) index of the oldest frame still available."""
        deadline = time.monotonic() + max(0.0, timeout)
        with self._cond:
            while self._head <= index:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
        for _ in range(_RETRIES):
            oldest = max(0, self._claimed - self.capacity)
            if index < oldest:
                return oldest
            s = index % self.capacity
            img = self._img[s].copy()
            slot = FrameSlot(index, img, float(self._t[s]), int(self._fid[s]), float(self._arrival[s]),
                             int(self._gapb[s]), bool(self._ffc[s]))
            if self._claimed - self.capacity <= index:
                return slot
        return max(0, self._claimed - self.capacity)
