"""Camera emulators: stand-ins for the thermal camera with the timing faults of the real thing.

- :class:`EmuCamera` — a :class:`~thermod.drivers.camera_base.CameraSource` that can go wherever a GigE
  (Aravis) or V4L2 source goes. Frames come from an injectable provider, are delivered in real time at
  ``fps`` with a transport latency, carry device timestamps in ns on a device clock with offset and
  drift, and 16-bit block ids that wrap 65535 → 1 (0 is invalid). Transmission losses and a consumer
  that falls behind the buffer pool show up as id gaps, exactly as a driver sees them. Flat-field
  corrections on a schedule (:class:`FFCSchedule`): frozen frames flagged ``ffc``, then an offset step.
- :class:`EmuV4L2Device` / :class:`EmuV4L2Capture` — a ``cv2.VideoCapture``-compatible Y16 V4L2 device
  for the :class:`~thermod.drivers.v4l2_camera.V4L2Camera` capture seam: FOURCC/CONVERT_RGB semantics,
  frames returned as flat uint8 bytes like OpenCV's V4L2 backend (or uint16 / [H, 2W] variants),
  telemetry rows, ``CAP_PROP_POS_MSEC`` buffer timestamps, a bounded buffer queue, unplug/replug.

Timing model shared by both: frame k's last row is read at ``T_k = origin + (k + 1) / fps`` (host
CLOCK_MONOTONIC, the truth); it reaches the consumer at ``T_k + latency`` at the earliest.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from thermod.drivers.camera_base import CameraSource, Frame, FrameIdTracker
from thermod.drivers.v4l2_camera import BOSON_FFC_IN_PROGRESS, BOSON_STATUS_WORD
from thermod.errors import DeviceError
from thermod.io.clock import ClockMapper

FrameProvider = Callable[[float], np.ndarray]


def make_provider(frames) -> Callable[[int, float], np.ndarray]:
    """Normalise a frame source to ``f(k, t) -> uint16 [H, W]``.

    ``frames``: a [N, H, W] array or a sequence of [H, W] arrays (looped by frame index), a single
    [H, W] array (static scene), a callable ``t -> image`` taking the frame's true host time ``T_k``
    (e.g. a simulator's pre-rendered loop indexed by time), or an object whose ``frame_at(k)`` gives
    frame index k (the simulated payload: its loop plus fresh temporal noise). Float images are raw
    counts: rounded and clipped to the 16-bit ADC range, as the detector's digitiser would.
    """
    frame_at = getattr(frames, "frame_at", None)
    if callable(frame_at):
        return lambda k, t: _to_u16(frame_at(k))
    if callable(frames):
        return lambda k, t: _to_u16(frames(t))
    if isinstance(frames, np.ndarray):
        if frames.ndim == 2:
            img = _to_u16(frames)
            return lambda k, t: img
        if frames.ndim == 3 and len(frames):
            stack = frames if frames.dtype == np.uint16 else None
            return (lambda k, t: stack[k % len(stack)]) if stack is not None else \
                (lambda k, t: _to_u16(frames[k % len(frames)]))
    if isinstance(frames, Sequence) and len(frames) and all(np.ndim(f) == 2 for f in frames):
        conv = [_to_u16(np.asarray(f)) for f in frames]
        return lambda k, t: conv[k % len(conv)]
    raise DeviceError(f"emulated camera: frames must be a [N, H, W] / [H, W] array, a list of [H, W] arrays "
                      f"or a callable t -> image, got {type(frames).__name__} "
                      f"{getattr(frames, 'shape', '')}")


def _offset(img: np.ndarray, counts: float) -> np.ndarray:
    """``img`` + ``counts``, clipped to the 16-bit ADC range (a new copy only when counts ≠ 0)."""
    if counts == 0:
        return img
    return np.clip(img.astype(np.float32) + np.float32(counts), 0, 65535).round().astype(np.uint16)


def _to_u16(img) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype == np.uint16:
        return img
    if img.ndim != 2:
        raise DeviceError(f"emulated camera: frame provider returned shape {img.shape}, expected [H, W]")
    return np.clip(np.rint(img), 0, 65535).astype(np.uint16)


class FFCSchedule:
    """Flat-field corrections (shutter/NUC) every ``interval_s``, each ``duration_s`` long.

    FFC ``j`` (j = 1, 2, ...) runs over ``[origin + j·interval_s, origin + j·interval_s + duration_s)``
    (host time). A frame read inside it shows the last frame read before it began (the camera freezes
    its output, as Boson/Tau cores do by default) and is flagged ``ffc``; afterwards the new NUC leaves
    a small offset: ``step_counts`` after odd-numbered FFCs, 0 after even ones (bounded, never drifting).
    """

    def __init__(self, interval_s: float, duration_s: float, step_counts: float = 0.0, origin: float = 0.0):
        if not (interval_s > duration_s > 0 and math.isfinite(interval_s)):
            raise DeviceError(f"FFC schedule: need interval_s > duration_s > 0, got {interval_s!r}, "
                              f"{duration_s!r}")
        self.interval_s, self.duration_s = float(interval_s), float(duration_s)
        self.step_counts, self.origin = float(step_counts), float(origin)

    def event(self, t: float) -> int:
        """Number of the last FFC begun at or before host time ``t`` (0: none yet)."""
        return max(0, math.floor((t - self.origin) / self.interval_s + 1e-12))

    def active(self, t: float) -> bool:
        """Whether an FFC is running at host time ``t``."""
        j = self.event(t)
        return j >= 1 and t - (self.origin + j * self.interval_s) < self.duration_s

    def offset(self, t: float) -> float:
        """NUC offset (counts) of a frame read at ``t`` outside an FFC."""
        return self.step_counts if self.event(t) % 2 else 0.0

    def start(self, j: int) -> float:
        return self.origin + j * self.interval_s


class _Timeline:
    """Frames completing at ``origin + (k + 1) / fps``, a pool of ``n_buffers`` filled buffers, and losses.

    ``take(now)`` dequeues the oldest filled frame that has arrived by ``now``: frames that completed while
    every buffer was full are dropped (the consumer was too slow), as are frames in ``drop`` / drawn with
    probability ``drop_prob`` (lost in transport).
    """

    def __init__(self, fps: float, origin: float, latency_s: float, n_buffers: int, drop=(), drop_prob=0.0,
                 seed=0):
        self.fps, self.origin, self.latency = float(fps), float(origin), float(latency_s)
        self.n_buffers = int(n_buffers)
        self.drop = set(drop)
        self.drop_prob = float(drop_prob)
        self.rng = np.random.default_rng(seed)
        self.produced = 0                       # next frame index the "device" will complete
        self.filled: deque[int] = deque()
        self.lost_transport = 0
        self.lost_overrun = 0
        self.dropped: deque[int] = deque(maxlen=100_000)   # indices of the most recent lost frames (truth)

    def completes(self, k: int) -> float:
        return self.origin + (k + 1) / self.fps

    def skip_to(self, t: float) -> None:
        """Start streaming at host time ``t``: frames completed before it are not part of the stream."""
        self.produced = max(self.produced, math.ceil((t - self.origin) * self.fps - 1 + 1e-9))

    def _advance(self, now: float) -> None:
        latest = math.floor((now - self.latency - self.origin) * self.fps - 1 + 1e-9)  # arrived by now
        if latest - self.produced > 100_000:   # consumer absent for ages: account in bulk
            skip = latest - self.produced - self.n_buffers
            self.lost_overrun += skip
            self.produced += skip
        while self.produced <= latest:
            k = self.produced
            self.produced += 1
            if k in self.drop or (self.drop_prob and self.rng.random() < self.drop_prob):
                self.lost_transport += 1
                self.dropped.append(k)
            elif len(self.filled) < self.n_buffers:
                self.filled.append(k)
            else:
                self.lost_overrun += 1
                self.dropped.append(k)

    def lost_between(self, a: int, b: int) -> int:
        """Frames lost (transport or overrun) with index in (a, b): the truth for gap counting."""
        return sum(1 for k in self.dropped if a < k < b)

    def take(self, now: float) -> int | None:
        self._advance(now)
        return self.filled.popleft() if self.filled else None

    def next_arrival(self) -> float:
        """Earliest host time at which another frame can be taken."""
        return self.completes(self.produced) + self.latency


class EmuCamera(CameraSource):
    """Simulated GigE-style camera source (see module docstring).

    Parameters
    ----------
    frames
        Frame provider (see :func:`make_provider`).
    fps
        Frame rate in Hz.
    drift_ppm
        Device oscillator error: the device clock advances ``(1 + drift_ppm·1e-6)`` ns per true ns.
    device_offset_ns
        Device clock reading at ``origin`` (a camera counts from its power-up, not from the host's epoch).
    first_frame_id
        Raw 16-bit block id of frame 0 (e.g. 65500 to cross the wrap soon).
    latency_s, jitter_s
        Transport delay: fixed part plus an exponential part with this mean.
    n_buffers
        Buffer pool; a consumer more than this many frames behind loses the newest frames.
    drop, drop_prob
        Frame indices lost in transport, and/or a per-frame loss probability.
    invalid_ids
        Frame indices delivered with block id 0 (an invalid id, as some cameras send on errors).
    origin
        Host time of the timeline origin (frame k completes at ``origin + (k+1)/fps``); None = at
        ``start()``. Pass the same origin to a gyro emulator to share one truth timeline.
    ffc
        Flat-field corrections (:class:`FFCSchedule`, on host time), or None for a camera that never
        runs one.
    """

    def __init__(self, frames, fps: float = 50.0, *, drift_ppm: float = 0.0,
                 device_offset_ns: int = 7_000_000_000, first_frame_id: int = 1, latency_s: float = 0.002,
                 jitter_s: float = 0.0002,
                 n_buffers: int = 8, drop: Sequence[int] = (), drop_prob: float = 0.0,
                 invalid_ids: Sequence[int] = (), origin: float | None = None, seed: int = 0,
                 name: str = "emu-camera", ffc: FFCSchedule | None = None):
        if not (fps > 0 and math.isfinite(fps)):
            raise DeviceError(f"{name}: fps must be > 0, got {fps!r}")
        if not 1 <= int(first_frame_id) <= 65535:
            raise DeviceError(f"{name}: first_frame_id must be a valid 16-bit block id 1..65535, got "
                              f"{first_frame_id!r}")
        self.provider = make_provider(frames)
        self.fps = float(fps)
        self.drift = float(drift_ppm) * 1e-6
        self.device_offset_ns = int(device_offset_ns)
        self.first_frame_id = int(first_frame_id)
        self.latency_s, self.jitter_s = float(latency_s), float(jitter_s)
        self.n_buffers = int(n_buffers)
        self.drop, self.drop_prob = tuple(drop), float(drop_prob)
        self.invalid_ids = set(invalid_ids)
        self.origin = origin
        self.seed = seed
        self.name = name
        self.rng = np.random.default_rng(seed)
        self.timeline: _Timeline | None = None
        self.tracker = FrameIdTracker()
        self.clock = ClockMapper(1e-9, name=f"{name} timestamp")
        self._pending: tuple[int, float] | None = None      # frame taken from the pool, awaiting its arrival
        self._lock = threading.Lock()
        self._running = False
        self.ffc = ffc
        self._ffc_event = 0                                  # last FFC whose frames were delivered
        self.counters = {"delivered": 0, "ffc_frames": 0, "ffc_events": 0}

    # -- device truth (for tests and the simulator) --------------------------------------------
    def true_time(self, k: int) -> float:
        """Host time at which frame index ``k``'s last row was read (the truth the driver estimates)."""
        return self.timeline.completes(k)

    def raw_frame_id(self, k: int) -> int:
        """The 16-bit block id the device puts on frame index ``k`` (wraps 65535 → 1; 0 never valid)."""
        return (self.first_frame_id - 1 + k) % 65535 + 1

    def device_ticks(self, t_host: float) -> int:
        """Device clock (ns) at true host time ``t_host``."""
        return self.device_offset_ns + int(round((t_host - self.timeline.origin) * (1.0 + self.drift) * 1e9))

    # -- CameraSource ---------------------------------------------------------------------------
    def start(self) -> None:
        with self._lock:
            if self._running:
                return
            now = time.monotonic()
            origin = now if self.origin is None else float(self.origin)
            self.timeline = _Timeline(self.fps, origin, self.latency_s, self.n_buffers, self.drop,
                                      self.drop_prob, self.seed)
            self.timeline.skip_to(now)
            self._running = True

    def stop(self) -> None:
        with self._lock:
            self._running = False

    def poll(self, timeout: float) -> Frame | None:
        deadline = time.monotonic() + max(0.0, timeout)
        with self._lock:
            if not self._running:
                raise DeviceError(f"{self.name}: poll() before start()")
            while True:
                if self._pending is None:
                    now = time.monotonic()
                    k = self.timeline.take(now)
                    if k is None:
                        wake = self.timeline.next_arrival()
                        if wake > deadline:
                            time.sleep(max(0.0, deadline - now))
                            return None
                        time.sleep(max(0.0, wake - now))
                        continue
                    jitter = self.rng.exponential(self.jitter_s) if self.jitter_s > 0 else 0.0
                    self._pending = (k, self.timeline.completes(k) + self.latency_s + jitter)
                k, due = self._pending
                now = time.monotonic()
                if due > now:
                    if due > deadline:
                        time.sleep(max(0.0, deadline - now))
                        return None
                    time.sleep(due - now)
                self._pending = None
                return self._deliver(k)

    def _deliver(self, k: int) -> Frame:
        arrival = time.monotonic()
        t_true = self.timeline.completes(k)
        ticks = self.device_ticks(t_true)
        raw_id = 0 if k in self.invalid_ids else self.raw_frame_id(k)
        frame_id, gap = self.tracker.update(raw_id)
        self.clock.observe(ticks, arrival)
        image, in_ffc = self._image(k, t_true)
        self.counters["delivered"] += 1
        return Frame(image=image, t=float(self.clock.to_host(ticks)), frame_id=frame_id, device_ts=ticks,
                     arrival=arrival, gap_before=gap, ffc=in_ffc)

    def ffc_truth(self, k: int) -> bool:
        """Whether frame index ``k`` is read during a flat-field correction (the schedule's truth)."""
        return self.ffc is not None and self.ffc.active(self.timeline.completes(k))

    def _image(self, k: int, t_true: float) -> tuple[np.ndarray, bool]:
        sched = self.ffc
        if sched is None:
            return self.provider(k, t_true), False
        if sched.active(t_true):
            j = sched.event(t_true)
            if j != self._ffc_event:
                self._ffc_event = j
                self.counters["ffc_events"] += 1
            self.counters["ffc_frames"] += 1
            # frozen: the last frame read before this FFC began, with the NUC it had
            k_frozen = math.ceil((sched.start(j) - self.timeline.origin) * self.fps - 1 - 1e-9) - 1
            t_frozen = self.timeline.completes(k_frozen)
            return _offset(self.provider(k_frozen, t_frozen), sched.offset(t_frozen)), True
        return _offset(self.provider(k, t_true), sched.offset(t_true)), False

    def stats(self) -> dict:
        tl = self.timeline
        out = {"state": "streaming" if self._running else "stopped", "fps": self.fps, **self.counters,
               **self.tracker.stats(), "clock_drift_ppm": self.clock.drift_ppm,
               "clock_residual_s": self.clock.residual_std_s, "clock_resets": self.clock.resets}
        if tl is not None:
            out.update(lost_transport=tl.lost_transport, lost_overrun=tl.lost_overrun)
        return out


# ------------------------------------------------------------------ V4L2 (cv2.VideoCapture seam)
_CV = None


def _cv():
    global _CV
    if _CV is None:
        import cv2

        _CV = cv2
    return _CV


class EmuV4L2Device:
    """A Y16 V4L2 camera (e.g. FLIR Boson 640 with 2 telemetry rows: 640×514) behind a device path.

    Use ``capture_factory=dev.open`` on :class:`~thermod.drivers.v4l2_camera.V4L2Camera`.

    Parameters
    ----------
    frames
        Image provider (see :func:`make_provider`), images of ``width × height`` (without telemetry).
    path
        The device path this emulator answers to (anything else fails to open, like a wrong node).
    fps_modes
        Frame rates the device accepts (the first is the default).
    telemetry_rows
        ``(top, bottom)`` telemetry lines added around the image; each holds a recognisable pattern
        (0xFFFF fill with the frame counter in words 0–1) that must never reach a deblurred frame.
        The first line carries a Boson status word (word 38: FFC state in bits 0–1, see
        `thermod.drivers.v4l2_camera.BOSON_STATUS_WORD`).
    ffc_frames
        Frame indices during which the telemetry reports "FFC in progress" (state 2; "complete",
        3, otherwise).
    layout
        What ``retrieve`` returns for Y16 with CONVERT_RGB off: ``"flat"`` — uint8 [1, 2·W·H] raw
        bytes (OpenCV's V4L2 backend for formats it does not convert), ``"rows"`` — uint8 [H, 2W],
        ``"u16"`` — uint16 [H, W].
    clock_offset_s, drift_ppm
        Buffer timestamps are ``(T_k − origin)(1 + drift) + origin + clock_offset_s`` in ms: the kernel's
        monotonic clock by default (offset 0, no drift); a UVC hardware clock otherwise.
    n_buffers
        Driver buffer queue (OpenCV's default 4): frames beyond it are dropped while the reader lags.
    """

    def __init__(self, frames, *, path: str = "/dev/video0", width: int = 640, height: int = 512,
                 fps_modes: Sequence[float] = (30.0, 60.0, 9.0), telemetry_rows: tuple[int, int] = (0, 0),
                 layout: str = "flat", clock_offset_s: float = 0.0, drift_ppm: float = 0.0,
                 latency_s: float = 0.001, n_buffers: int = 4, drop: Sequence[int] = (), seed: int = 0,
                 ffc_frames: Sequence[int] = ()):
        if layout not in ("flat", "rows", "u16"):
            raise DeviceError(f"emulated V4L2 device: layout must be 'flat', 'rows' or 'u16', got {layout!r}")
        self.provider = make_provider(frames)
        self.path = path
        self.width, self.height = int(width), int(height)
        self.top, self.bottom = (int(v) for v in telemetry_rows)
        self.raw_height = self.height + self.top + self.bottom
        self.fps_modes = tuple(float(f) for f in fps_modes)
        self.layout = layout
        self.clock_offset_s, self.drift = float(clock_offset_s), float(drift_ppm) * 1e-6
        self.latency_s = float(latency_s)
        self.n_buffers = int(n_buffers)
        self.drop = tuple(drop)
        self.ffc_frames = set(ffc_frames)
        self.seed = seed
        self.plugged = True
        self.opened = 0
        self.captures: list[EmuV4L2Capture] = []

    def open(self, path, api_preference=None) -> EmuV4L2Capture:
        """``cv2.VideoCapture(path, cv2.CAP_V4L2)`` for this device."""
        cap = EmuV4L2Capture(self, path)
        self.captures.append(cap)
        return cap

    def unplug(self) -> None:
        self.plugged = False

    def replug(self) -> None:
        self.plugged = True

    def telemetry(self, k: int) -> np.ndarray:
        rows = np.full((self.top + self.bottom, self.width), 0xFFFF, np.uint16)
        if len(rows):
            rows[:, 0] = k & 0xFFFF
            rows[:, 1] = (k >> 16) & 0xFFFF
            if rows.shape[1] > BOSON_STATUS_WORD:
                state = BOSON_FFC_IN_PROGRESS if k in self.ffc_frames else 3    # 3: FFC complete
                rows[0, BOSON_STATUS_WORD] = 0xFFFC | state
        return rows


class EmuV4L2Capture:
    """``cv2.VideoCapture`` look-alike for one open of an :class:`EmuV4L2Device` (V4L2 backend semantics)."""

    def __init__(self, device: EmuV4L2Device, path):
        cv2 = _cv()
        self.dev = device
        self._open = device.plugged and str(path) == device.path
        if self._open:
            device.opened += 1
        self.props = {cv2.CAP_PROP_FOURCC: float(_fourcc("YUYV")), cv2.CAP_PROP_CONVERT_RGB: 1.0,
                      cv2.CAP_PROP_FRAME_WIDTH: float(device.width), cv2.CAP_PROP_FRAME_HEIGHT: 480.0,
                      cv2.CAP_PROP_FPS: device.fps_modes[0], cv2.CAP_PROP_POS_MSEC: 0.0,
                      cv2.CAP_PROP_READ_TIMEOUT_MSEC: 10000.0,
                      cv2.CAP_PROP_BUFFERSIZE: float(device.n_buffers)}
        self.timeline: _Timeline | None = None
        self._grabbed: int | None = None

    # cv2.VideoCapture API -------------------------------------------------------------------------
    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return self._open

    def release(self) -> None:
        self._open = False

    def get(self, prop: int) -> float:
        return float(self.props.get(prop, 0.0)) if self._open else 0.0

    def set(self, prop: int, value: float) -> bool:
        cv2 = _cv()
        if not self._open:
            return False
        if self.timeline is not None and prop in (cv2.CAP_PROP_FOURCC, cv2.CAP_PROP_FRAME_WIDTH,
                                                  cv2.CAP_PROP_FRAME_HEIGHT, cv2.CAP_PROP_FPS):
            return False                        # format changes while streaming: EBUSY
        if prop == cv2.CAP_PROP_FOURCC:
            if _fourcc_str(int(value)) not in ("Y16 ", "YUYV"):
                return False
            self.props[prop] = float(int(value))
            # A format change re-initialises the capture: conversion to RGB is back on.
            self.props[cv2.CAP_PROP_CONVERT_RGB] = 1.0
            if _fourcc_str(int(value)) == "Y16 ":
                self.props[cv2.CAP_PROP_FRAME_HEIGHT] = float(self.dev.raw_height)
            return True
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            return float(value) == self.dev.width     # a real driver keeps its nearest supported size
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:
            y16 = _fourcc_str(int(self.props[cv2.CAP_PROP_FOURCC])) == "Y16 "
            if y16 and float(value) == self.dev.raw_height:
                self.props[prop] = float(value)
                return True
            return False
        if prop == cv2.CAP_PROP_FPS:
            if float(value) in self.dev.fps_modes:
                self.props[prop] = float(value)
                return True
            return False
        if prop in (cv2.CAP_PROP_CONVERT_RGB, cv2.CAP_PROP_READ_TIMEOUT_MSEC, cv2.CAP_PROP_BUFFERSIZE):
            self.props[prop] = float(value)
            return True
        return False

    def grab(self) -> bool:
        cv2 = _cv()
        if not (self._open and self.dev.plugged):
            return False
        if self.timeline is None:             # STREAMON on the first read, as OpenCV does
            now = time.monotonic()
            self.timeline = _Timeline(self.props[cv2.CAP_PROP_FPS], now, self.dev.latency_s,
                                      int(self.props[cv2.CAP_PROP_BUFFERSIZE]), self.dev.drop,
                                      seed=self.dev.seed)
        deadline = time.monotonic() + self.props[cv2.CAP_PROP_READ_TIMEOUT_MSEC] / 1000.0
        while True:
            now = time.monotonic()
            k = self.timeline.take(now)
            if k is not None:
                break
            wake = self.timeline.next_arrival()
            if wake > deadline:
                time.sleep(max(0.0, deadline - now))
                return False                   # select() timeout
            time.sleep(max(0.0, wake - now))
            if not self.dev.plugged:
                return False
        tl = self.timeline
        t_true = tl.completes(k)
        device_s = tl.origin + (t_true - tl.origin) * (1.0 + self.dev.drift) + self.dev.clock_offset_s
        self.props[cv2.CAP_PROP_POS_MSEC] = 1000.0 * device_s
        self._grabbed = k
        return True

    def retrieve(self, image=None, flag: int = 0):
        cv2 = _cv()
        if self._grabbed is None or not self._open:
            return False, None
        k, self._grabbed = self._grabbed, None
        img = self.dev.provider(k, self.timeline.completes(k))
        if img.shape != (self.dev.height, self.dev.width):
            raise DeviceError(f"emulated V4L2 device: provider frame is {img.shape}, device is "
                              f"{(self.dev.height, self.dev.width)}")
        tel = self.dev.telemetry(k)
        raw = np.concatenate([tel[:self.dev.top], img, tel[self.dev.top:]], axis=0).astype("<u2")
        if _fourcc_str(int(self.props[cv2.CAP_PROP_FOURCC])) != "Y16 ":
            return True, np.repeat((raw >> 8).astype(np.uint8)[..., None], 3, axis=2)   # YUYV → BGR
        if self.props[cv2.CAP_PROP_CONVERT_RGB]:
            # OpenCV converts Y16 to 8-bit BGR when conversion is left on: the 16-bit counts are gone
            return True, np.repeat((raw >> 8).astype(np.uint8)[..., None], 3, axis=2)
        if self.dev.layout == "u16":
            return True, raw
        b = raw.view(np.uint8)
        if self.dev.layout == "flat":
            return True, b.reshape(1, -1).copy()
        return True, b.reshape(raw.shape[0], -1).copy()

    def read(self, image=None):
        if not self.grab():
            return False, None
        return self.retrieve()


def _fourcc(s: str) -> int:
    return sum(ord(c) << (8 * i) for i, c in enumerate(s))


def _fourcc_str(code: int) -> str:
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
