"""Replay of a format-v1 recording (docs/design.md §3) as a camera source and a gyro source.

Both sources of one recording share a :class:`ReplaySession`: one timeline re-based to the host clock
(the recording's first sample maps to ``time.monotonic()`` at the first ``start()``), so the relative
timing of frames and gyro samples — and with it ``time_offset_s`` — is exactly that of the
recording. ``ReplayCamera(path)`` and ``ReplayGyro(path)`` built separately join the same session.

Pacing: ``speed = 1`` delivers items when their re-based time comes; ``speed = s`` delivers ``s``
times faster (or slower) with the recording's time scale kept in the reported times (rates are
physical rad/s); ``speed = math.inf`` runs in lockstep as fast as the consumers poll (a frame only
once the gyro has delivered up to its time, the gyro at most ``lead_s`` ahead). ``loop=True``
repeats the recording with times, frame ids and sequence numbers continuing.

Calibration: both sources expose the recording's own (``calibration``); `thermod run` deblurs with it
unless ``[sources.camera] calibration = "config"``. In full: docs/design.md §5, "Gyro sources".
"""

from __future__ import annotations

import math
import os
import threading
import time
import weakref
from pathlib import Path

import h5py
import numpy as np

from thermod.drivers.camera_base import CameraSource, Frame
from thermod.drivers.gyro_base import GyroBatch, GyroSource
from thermod.errors import DeviceError, RecordingError
from thermod.io import recording as recmod

_SESSIONS: weakref.WeakValueDictionary = weakref.WeakValueDictionary()
_SESSIONS_LOCK = threading.Lock()


class _LazyFrames:
    """``frames[i]`` read from the HDF5 file on demand (chunked one frame per chunk: one chunk per read)."""

    def __init__(self, path: Path):
        self.path = path
        self._f = h5py.File(path, "r")
        self._d = self._f["camera/frames"]
        self.shape = self._d.shape
        self.dtype = self._d.dtype
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, i: int) -> np.ndarray:
        with self._lock:
            return self._d[i]

    def close(self) -> None:
        self._f.close()


def _load(path: Path):
    """Times, gyro samples and calibration in memory; frames lazily. Validated like recording.read."""
    t, gyro_t, gyro_rate, calib = recmod.read_timeline(path)
    return t, gyro_t, gyro_rate, calib


class ReplaySession:
    """One recording, one re-based timeline, shared by its :class:`ReplayCamera` and :class:`ReplayGyro`.

    Parameters
    ----------
    source
        A recording path, or an in-memory :class:`thermod.io.recording.Recording`.
    speed
        Pacing factor (1 = real time; ``math.inf`` = as fast as possible, lockstep).
    loop
        Repeat the recording endlessly.
    lead_s
        As-fast-as-possible mode: how far the gyro may run ahead of the last frame handed out.
    """

    def __init__(self, source, *, speed: float = 1.0, loop: bool = False, lead_s: float = 0.25):
        if not (speed > 0):
            raise DeviceError(f"replay: speed must be > 0 (math.inf = as fast as possible), got {speed!r}")
        self.speed = float(speed)
        self.loop = bool(loop)
        self.lead_s = float(lead_s)
        if isinstance(source, recmod.Recording):
            source.validate()
            self.path = None
            self.name = "replay:<memory>"
            self.frames = source.frames
            self.t, self.gyro_t = np.asarray(source.t, np.float64), np.asarray(source.gyro_t, np.float64)
            self.gyro_rate = np.asarray(source.gyro_rate, np.float32)
            self.calibration = source.calibration
        else:
            self.path = Path(source)
            self.name = f"replay:{self.path.name}"
            self.t, self.gyro_t, self.gyro_rate, self.calibration = _load(self.path)
            self.frames = _LazyFrames(self.path)
        c = self.calibration
        self.frame_period = 1.0 / c.frame_rate_hz
        self.gyro_period = 1.0 / c.rate_hz
        starts = [a[0] for a in (self.t, self.gyro_t) if len(a)]
        if not starts:
            raise RecordingError(self.path or "<memory>", "camera/t, gyro/t", "recording holds no frames and "
                                 "no gyro samples: nothing to replay")
        self.r0 = min(starts)
        ends = [a[-1] + p for a, p in ((self.t, self.frame_period), (self.gyro_t, self.gyro_period))
                if len(a)]
        self.loop_period = max(ends) - self.r0
        self.origin: float | None = None
        self.cond = threading.Condition()
        # lockstep bookkeeping (as-fast-as-possible mode): re-based time handed out so far, per source
        self.gyro_active = self.camera_active = False
        self.gyro_done = self.camera_done = False
        self.gyro_next = -math.inf       # re-based time of the next sample the gyro will hand out
        self.camera_next = -math.inf     # re-based time of the next frame the camera wants to hand out

    @property
    def fast(self) -> bool:
        return math.isinf(self.speed)

    def begin(self) -> None:
        with self.cond:
            if self.origin is None:
                self.origin = time.monotonic()

    def rebased(self, r: float | np.ndarray, lap: int):
        """Reported host time of recording time ``r`` in loop ``lap`` (recording time scale)."""
        return self.origin + (r - self.r0) + lap * self.loop_period

    def due(self, t_rebased: float) -> float:
        """Host time at which an item with re-based time ``t_rebased`` is delivered."""
        return self.origin + (t_rebased - self.origin) / self.speed

    def position(self, times: np.ndarray, lap: int, i: int, catch_up_s: float = 0.1) -> tuple[int, int]:
        """(lap, index) of the first item of ``times`` not more than ``catch_up_s`` overdue now, never
        before (lap, i). A paced source (re)started late joins the stream where a live device would be;
        in as-fast-as-possible mode nothing is skipped."""
        if self.fast or not len(times):
            return lap, i
        target = self.origin + (time.monotonic() - self.origin) * self.speed - catch_up_s * self.speed
        k = math.floor((target - self.origin) / self.loop_period) if self.loop else 0
        if self.loop and k > lap:
            lap, i = k, 0
        r_target = target - (self.origin - self.r0) - lap * self.loop_period    # recording time
        j = int(np.searchsorted(times, r_target, side="left"))
        if self.loop and j >= len(times):
            return lap + 1, 0
        return lap, max(i, j)

    def camera(self) -> ReplayCamera:
        return ReplayCamera(self)

    def gyro(self) -> ReplayGyro:
        return ReplayGyro(self)

    def close(self) -> None:
        if isinstance(self.frames, _LazyFrames):
            self.frames.close()


def _session(source, speed, loop, session) -> ReplaySession:
    if session is not None:
        return session
    if isinstance(source, ReplaySession):
        return source
    if isinstance(source, recmod.Recording):
        return ReplaySession(source, speed=speed, loop=loop)
    key = (os.path.realpath(os.fspath(source)), float(speed), bool(loop))
    with _SESSIONS_LOCK:
        s = _SESSIONS.get(key)
        if s is None:
            s = ReplaySession(source, speed=speed, loop=loop)
            _SESSIONS[key] = s
        return s


def _wait(cond: threading.Condition, until: float) -> None:
    """Sleep on the session's condition until ``until`` (host time) or a notification."""
    remaining = until - time.monotonic()
    if remaining > 0:
        cond.wait(remaining)


class _ReplayStream:
    """What a replayed camera and gyro share: their place (lap, index) in the session's timeline,
    start/stop, and the lockstep fields ``<role>_active``, ``<role>_done``, ``<role>_next`` of the session."""

    role: str                # "camera" or "gyro": names this source's lockstep fields on the session
    session: ReplaySession

    @property
    def calibration(self):
        """The calibration the recording carries (the gyro ↔ camera relation its timeline was made with)."""
        return self.session.calibration

    def _attach(self, source, speed: float, loop: bool, session: ReplaySession | None) -> None:
        self.session = _session(source, speed, loop, session)
        self.name = f"{self.session.name} {self.role}"
        if len(self._times) == 0:
            what = "frames (camera/t)" if self.role == "camera" else "gyro samples (gyro/t)"
            raise DeviceError(f"{self.name}: the recording holds no {what}: nothing to replay as its "
                              f"{self.role}")
        self._i = 0           # next item index within the lap
        self._lap = 0
        self._running = False

    @property
    def _times(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def finished(self) -> bool:
        s = self.session
        return not s.loop and self._i >= len(self._times)

    def _seek(self, lap: int, i: int) -> None:
        self._lap, self._i = lap, i

    def start(self) -> None:
        s = self.session
        s.begin()
        with s.cond:
            self._seek(*s.position(self._times, self._lap, self._i))
            setattr(s, f"{self.role}_active", True)
            self._publish_next()
            s.cond.notify_all()
        self._running = True

    def stop(self) -> None:
        s = self.session
        with s.cond:
            setattr(s, f"{self.role}_active", False)
            s.cond.notify_all()
        self._running = False

    def _check_started(self) -> None:
        if not self._running:
            raise DeviceError(f"{self.name}: poll() before start()")

    def _drained(self, deadline: float) -> bool:
        """Under ``session.cond``: nothing more to hand out? Then say so to the other source and wait
        out ``deadline`` (the caller returns None)."""
        s = self.session
        if len(self._times) and not self.finished:
            return False
        setattr(s, f"{self.role}_done", True)
        s.cond.notify_all()
        _wait(s.cond, deadline)
        return True

    def _publish_next(self) -> None:
        s = self.session
        done = self.finished
        nxt = math.inf if done else float(s.rebased(self._times[self._i], self._lap))
        setattr(s, f"{self.role}_done", done)
        setattr(s, f"{self.role}_next", nxt)

    def _stream_stats(self) -> dict:
        s = self.session
        return {"state": "finished" if self.finished else ("streaming" if self._running else "stopped"),
                "recording": str(s.path) if s.path else "<memory>", "speed": s.speed}


class ReplayCamera(_ReplayStream, CameraSource):
    """Frames of a recording, re-timed (see module docstring). ``device_ts`` is the recorded time in ns."""

    role = "camera"

    def __init__(self, source, *, loop: bool = False, speed: float = 1.0,
                 session: ReplaySession | None = None):
        self._attach(source, speed, loop, session)
        self._last_t = math.nan
        self.counters = {"frames": 0, "laps": 0, "frames_lost": 0}

    @property
    def _times(self) -> np.ndarray:
        return self.session.t

    def poll(self, timeout: float) -> Frame | None:
        self._check_started()
        s = self.session
        deadline = time.monotonic() + max(0.0, timeout)
        n = len(s.t)
        with s.cond:
            while True:
                if self._drained(deadline):
                    return None
                t = float(s.rebased(s.t[self._i], self._lap))
                if s.fast:
                    # lockstep: every gyro sample up to this frame's time must be out first
                    ready = not s.gyro_active or s.gyro_done or s.gyro_next > t
                    until = deadline
                else:
                    until = s.due(t)
                    ready = time.monotonic() >= until
                if ready:
                    break
                if time.monotonic() >= deadline:
                    return None
                _wait(s.cond, min(until, deadline))
            i, lap = self._i, self._lap
            self._i += 1
            if self._i >= n and s.loop:
                self._i, self._lap = 0, self._lap + 1
                self.counters["laps"] += 1
            self._publish_next()
            s.cond.notify_all()
        image = np.asarray(s.frames[i])
        gap = 0
        if math.isfinite(self._last_t) and not (i == 0 and lap > 0):   # the loop seam is no loss
            gap = max(0, round((t - self._last_t) / s.frame_period) - 1)   # frames missing in the recording
        self._last_t = t
        self.counters["frames"] += 1
        self.counters["frames_lost"] += gap
        return Frame(image=image, t=t, frame_id=lap * n + i, device_ts=int(round(float(s.t[i]) * 1e9)),
                     arrival=time.monotonic(), gap_before=gap)

    def stats(self) -> dict:
        return {**self._stream_stats(), **self.counters}


class ReplayGyro(_ReplayStream, GyroSource):
    """Gyro samples of a recording as :class:`~thermod.drivers.gyro_base.GyroBatch` es (raw rad/s, gyro frame,
    times re-based to the host clock; batches split where the recording has gaps, flagged ``gap_before``).

    ``batch_s``: in paced modes a batch is handed out at most every ``batch_s`` (like a FIFO read);
    ``max_batch``: the largest batch (as-fast-as-possible mode).
    """

    role = "gyro"

    def __init__(self, source, *, loop: bool = False, speed: float = 1.0,
                 session: ReplaySession | None = None, batch_s: float = 0.004, max_batch: int = 256):
        super().__init__()
        self._attach(source, speed, loop, session)
        self.batch_s = float(batch_s)
        self.max_batch = int(max_batch)
        self._next_batch = 0.0
        self._seek_gap = 0           # samples skipped by a late (re)start: reported on the next batch
        s = self.session
        dt = np.diff(s.gyro_t)
        # index j starts a gap when the step before it exceeds 1.5 sample periods
        self._gap_at = np.flatnonzero(dt > 1.5 * s.gyro_period) + 1
        self._lost_at = {int(j): int(round(dt[j - 1] / s.gyro_period)) - 1 for j in self._gap_at}
        self._stats.update(laps=0)

    @property
    def _times(self) -> np.ndarray:
        return self.session.gyro_t

    def _seek(self, lap: int, i: int) -> None:
        skipped = (lap - self._lap) * len(self._times) + i - self._i
        if skipped:
            self._seek_gap = skipped
        self._lap, self._i = lap, i

    def poll(self, timeout: float) -> GyroBatch | None:
        self._check_started()
        s = self.session
        m = len(s.gyro_t)
        deadline = time.monotonic() + max(0.0, timeout)
        with s.cond:
            while True:
                if self._drained(deadline):
                    return None
                now = time.monotonic()
                if s.fast:
                    limit = s.camera_next + s.lead_s if s.camera_active else math.inf
                    # relative to this lap's start: recording time up to which samples may go out
                    r_limit = limit - s.rebased(s.r0, self._lap) + s.r0
                    until = deadline
                else:
                    if now < self._next_batch:
                        if self._next_batch > deadline:
                            _wait(s.cond, deadline)
                            return None
                        _wait(s.cond, self._next_batch)
                        continue
                    # recording time due by now in this lap
                    r_limit = s.r0 + (now - s.origin) * s.speed - self._lap * s.loop_period
                    until = s.due(float(s.rebased(s.gyro_t[self._i], self._lap)))
                j = int(np.searchsorted(s.gyro_t, r_limit, side="right"))
                j = min(j, self._i + self.max_batch)
                nxt = self._gap_at[np.searchsorted(self._gap_at, self._i, side="right"):][:1]
                if len(nxt) and nxt[0] < j:
                    j = int(nxt[0])                  # end the batch where the recording has a gap
                if j > self._i:
                    break
                if time.monotonic() >= deadline:
                    return None
                _wait(s.cond, min(until, deadline))
            i0, lap = self._i, self._lap
            t = s.rebased(s.gyro_t[i0:j], lap)
            n_lost = self._lost_at.get(i0, 0) + self._seek_gap
            batch = GyroBatch(t=np.asarray(t, np.float64), rate=s.gyro_rate[i0:j].copy(), seq=lap * m + i0,
                              gap_before=i0 in self._lost_at or self._seek_gap > 0, n_lost=n_lost)
            self._seek_gap = 0
            self._i = j
            if self._i >= m and s.loop:
                self._i, self._lap = 0, self._lap + 1
                self._stats["laps"] += 1
            self._publish_next()
            self._next_batch = time.monotonic() + self.batch_s
            s.cond.notify_all()
        return self._count_batch(batch)

    def stats(self) -> dict:
        return {**super().stats(), **self._stream_stats()}
