"""Camera source contract (docs/interfaces.md, "Camera sources") and the pieces every camera driver shares.

A camera source hands out :class:`Frame` objects from ``poll(timeout)``; the daemon's driver thread calls
it in a loop (sources own no delivery threads). Each driver maps its device clock to host
``CLOCK_MONOTONIC`` through `ClockMapper` (docs/design.md §2: never stamp a frame with its
read time) and counts lost frames from the device's frame ids with :class:`FrameIdTracker`.
"""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass

import numpy as np

from thermod.errors import DeviceError
from thermod.io.clock import ClockMapper

FRAME_ID_BITS = 16   # GigE Vision block ids (GVSP) and most USB cameras: 16 bits, 0 reserved as "invalid"


@dataclass
class Frame:
    """One raw frame as received.

    Attributes
    ----------
    image : uint16 [H, W] raw detector counts.
    t : host monotonic seconds when the LAST row was read, mapped from the device clock.
    frame_id : unwrapped frame counter (monotonic across id wraps).
    device_ts : device timestamp as received (ns for GigE, µs for V4L2), or None.
    arrival : host monotonic seconds when the driver received the frame.
    gap_before : number of frames lost just before this one (from frame-id gaps).
    ffc : the camera reports a flat-field correction (shutter closed / NUC update) in progress while
        it delivered this frame: the image is frozen or shows the shutter, not the scene.
    """

    image: np.ndarray
    t: float
    frame_id: int
    device_ts: int | None
    arrival: float
    gap_before: int = 0
    ffc: bool = False


class CameraSource(abc.ABC):
    """A source of :class:`Frame`; ``poll`` blocks at most ``timeout`` seconds and returns None on timeout.

    I/O failures raise :class:`thermod.errors.DeviceError` with a message saying what to check.
    Every source offers ``name``, ``clock`` (its device-clock mapping, or None when its times need
    none, e.g. a replay) and ``stats()``.
    """

    name: str = "camera"
    clock: ClockMapper | None = None     # device clock → host mapping, if the driver fits one

    @abc.abstractmethod
    def start(self) -> None: ...

    @abc.abstractmethod
    def stop(self) -> None: ...

    @abc.abstractmethod
    def poll(self, timeout: float) -> Frame | None: ...

    @abc.abstractmethod
    def stats(self) -> dict: ...

    def radiometry(self):
        """The camera's own counts → °C model (`thermod.physics.radiometry`), when it reports one (FLIR
        cameras expose Planck constants over GenICam); None otherwise. Read once, when asked."""
        return None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class FrameIdTracker:
    """Unwrap an n-bit device frame id whose value 0 is invalid (ids run ..., 2^n − 1, 1, 2, ...).

    ``update(raw)`` returns ``(frame_id, gap)``: the unwrapped id and the number of frames lost since the
    previous one. A jump backwards (or forwards by more than half the id space, which cannot be told apart
    from backwards) means the device restarted its counter: counted in ``resets``, no gap reported.
    An id of 0 is counted in ``invalid`` and takes the next expected id, so the stream stays numbered.
    """

    def __init__(self, bits: int = FRAME_ID_BITS):
        self.modulus = (1 << bits) - 1          # number of valid ids: 1 .. 2^n − 1
        self.last_raw: int | None = None
        self.frame_id = -1                      # unwrapped id of the last frame
        self.frames = 0
        self.lost = 0                           # frames lost in total
        self.gaps = 0                           # gap events
        self.invalid = 0
        self.resets = 0
        self.wraps = 0
        self.extended = False

    def update(self, raw: int) -> tuple[int, int]:
        raw = int(raw)
        self.frames += 1
        if raw > self.modulus and self.modulus == 0xFFFF and raw < 1 << 64:
            # GigE Vision 2 extended ids (64-bit block ids, no practical wrap): widen once
            self.modulus = (1 << 64) - 1
            self.extended = True
        if raw == 0 or raw > self.modulus or raw < 0:
            self.invalid += 1
            self.frame_id += 1
            if self.last_raw is not None:
                self.last_raw = self.last_raw % self.modulus + 1
            return self.frame_id, 0
        if self.last_raw is None:
            # first frame ever: adopt the device's numbering; after resync(): keep counting on
            self.frame_id = raw if self.frame_id < 0 else self.frame_id + 1
            self.last_raw = raw
            return self.frame_id, 0
        delta = (raw - self.last_raw) % self.modulus    # ids live in 1..modulus, so wrap modulo it
        if raw < self.last_raw and delta > 0 and delta <= self.modulus // 2:
            self.wraps += 1
        self.last_raw = raw
        if delta == 0 or delta > self.modulus // 2:
            self.resets += 1                            # duplicate, reorder or counter restart
            self.frame_id += 1
            return self.frame_id, 0
        gap = delta - 1
        if gap:
            self.gaps += 1
            self.lost += gap
        self.frame_id += delta
        return self.frame_id, gap

    def resync(self) -> None:
        """Forget the device's last id (after a reconnect its counter restarts); unwrapped ids continue."""
        self.last_raw = None

    def stats(self) -> dict:
        return {"frames": self.frames, "frames_lost": self.lost, "gap_events": self.gaps,
                "invalid_ids": self.invalid, "id_resets": self.resets, "id_wraps": self.wraps}


def as_uint16_image(data, height: int, width: int, device: str) -> np.ndarray:
    """Interpret what a capture backend returned as a uint16 [height, width] image, defensively.

    Accepts uint16 [H, W], uint16 flat/[1, N], and little-endian byte buffers (bytes, uint8 flat, [1, 2N],
    [H, 2W], [H, W, 2]) — some OpenCV builds and GenICam buffers hand 16-bit pixels over as raw bytes.
    Anything else (e.g. 8-bit 3-channel frames from an unhonoured Y16 request) raises DeviceError.
    """
    n = height * width
    if isinstance(data, bytes | bytearray | memoryview):
        data = np.frombuffer(data, dtype=np.uint8)
    if not isinstance(data, np.ndarray):
        raise DeviceError(f"{device}: expected an image array, got {type(data).__name__}")
    if data.dtype == np.uint16 and data.size == n:
        return data.reshape(height, width)
    if data.dtype == np.uint8 and data.size == 2 * n and (data.ndim < 3 or data.shape[-1] == 2):
        return np.ascontiguousarray(data).reshape(-1).view("<u2").reshape(height, width)
    hint = ""
    if data.ndim == 3 and data.shape[-1] == 3:
        hint = " (8-bit colour: the device ignored Y16/Mono16 or RGB conversion is still on)"
    raise DeviceError(f"{device}: expected a {height}×{width} 16-bit frame ({n} pixels, {2 * n} bytes), "
                      f"got dtype {data.dtype} shape {data.shape}{hint}")


def count_ffc(counters: dict, was_in_ffc: bool, in_ffc: bool) -> None:
    """Count a frame delivered during a flat-field correction (``ffc_frames``) and each correction that
    begins (``ffc_events``), given the state of the previous frame and of this one."""
    if in_ffc:
        counters["ffc_frames"] += 1
        if not was_in_ffc:
            counters["ffc_events"] += 1


def measured_rate_hz(arrivals) -> float:
    """Frame rate from the host arrival times of the latest frames (0 until three have arrived)."""
    n = len(arrivals)
    span = arrivals[-1] - arrivals[0] if n else 0.0
    return (n - 1) / span if n > 2 and span > 0 else 0.0


def clock_stats(clock: ClockMapper) -> dict:
    """The device-clock fit's health, for a driver's ``stats()``."""
    return {"clock_drift_ppm": clock.drift_ppm, "clock_residual_s": clock.residual_std_s,
            "clock_resets": clock.resets}


class Backoff:
    """When to retry opening a lost device: after ``first`` s, the wait doubling after each failed
    attempt up to ``longest`` s."""

    def __init__(self, first: float, longest: float):
        self.first, self.longest = float(first), float(longest)
        self.delay = self.first
        self.next_attempt = 0.0

    def restart(self, *, at_once: bool) -> None:
        """A new loss: the first attempt now (``at_once``) or after ``first`` s."""
        self.delay = self.first
        self.next_attempt = time.monotonic() + (0.0 if at_once else self.delay)

    def due(self, deadline: float) -> bool:
        """True when an attempt is due; else sleep towards it (never past ``deadline``) and say False."""
        now = time.monotonic()
        if now < self.next_attempt:
            time.sleep(max(0.0, min(deadline, self.next_attempt) - now))
            return False
        return True

    def failed(self) -> None:
        """An attempt failed: wait the current delay, and double it for the attempt after."""
        self.next_attempt = time.monotonic() + self.delay
        self.delay = min(2 * self.delay, self.longest)
