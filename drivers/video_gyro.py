"""A gyro source that has no gyro: the camera's rotation measured from its own frames.

``[sources.gyro] kind = "video"``. The daemon hands it every frame it receives (`offer`, from the camera
thread: the frame is shrunk to its working image there and queued); the gyro thread's `poll` registers
each against the one before (`thermod.motion.live.LiveTrack`) and returns the camera-frame rates as a
`GyroBatch` stamped with the frames' host times, so the frame clock is the gyro clock. The daemon runs
it with the camera's own gyro part (`Calibration.with_camera_gyro`). A frame's samples arrive with the next
frame: one frame period of added latency (two across a bridged interval: the daemon's wait for samples
is at least `samples_wait_s`). Registration failures leave holes, flagged ``gap_before``.
"""

from __future__ import annotations

import collections
import threading
import time

import numpy as np

from thermod.drivers.gyro_base import GyroBatch, GyroSource
from thermod.motion.live import DEFAULT_RATE_HZ, MAX_BRIDGED, LiveTrack
from thermod.motion.track import full_resolution
from thermod.restore.overlay import grown

REGISTER_S = 0.03         # allowed for a frame's registration before its samples are late (by corners
                          # ~7 ms, p99 12; by every pixel where they fail, ~10 ms more)
QUEUE_FRAMES = 8          # frames waiting for registration; beyond, the oldest is skipped (the next pair
                          # spans it: a longer interval, not a hole)
DELAY_WINDOW = 500        # registrations whose delay (offer → registered) `stats` summarises


class VideoGyro(GyroSource):
    """Rates from the camera's frames (module docstring). `calib`: the camera's intrinsics, τ and
    readout (`bind` replaces it before start when the calibration in force is another)."""

    motion_source = "video"

    def __init__(self, calib, *, rate_hz: float = DEFAULT_RATE_HZ, work_width: int = 160):
        super().__init__()
        self.name = "video (the camera's own frames)"
        self.rate_hz, self.work_width = float(rate_hz), int(work_width)
        self.track: LiveTrack | None = None
        self.bind(calib)
        self._frames: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._seq = 0
        self._stats.update(frames_offered=0, frames_skipped=0)
        self._delays: collections.deque = collections.deque(maxlen=DELAY_WINDOW)

    @staticmethod
    def samples_wait_s(frame_rate_hz: float) -> float:
        """How long a frame may wait for its samples: the next frame, one more across a bridged interval
        (`thermod.motion.live.MAX_BRIDGED`), and their registration."""
        return (1 + MAX_BRIDGED) / float(frame_rate_hz) + REGISTER_S

    def calibration_for(self, calib):
        """The calibration the daemon runs this source with: `calib`'s camera, the video's gyro part."""
        return calib.with_camera_gyro(self.rate_hz)

    def bind(self, calib) -> None:
        """Measure with this calibration's intrinsics, τ and readout."""
        self.track = LiveTrack(calib.intrinsics, tau_s=calib.tau_s, readout_s=calib.readout_s,
                               rate_hz=self.rate_hz, work_width=self.work_width)
        self._size = (int(calib.width), int(calib.height))
        self._overlay: tuple | None = None
        self._overlay_from = None

    def overlay(self) -> tuple | None:
        """The static overlay found so far at the frames' size, as (mask bool, grown mask uint8: what
        the solve inpaints, `thermod.restore.overlay`), or None. The same objects while the mask holds."""
        work = self.track.overlay.mask
        if work is None:
            return None
        if work is not self._overlay_from:
            mask = full_resolution(work, *self._size).astype(bool)
            if self._overlay is None or not np.array_equal(mask, self._overlay[0]):
                self._overlay = (mask, grown(mask))
            self._overlay_from = work
        return self._overlay

    def start(self) -> None:
        pass

    def stop(self) -> None:
        with self._cond:
            self._frames.clear()
            self._cond.notify_all()

    def offer(self, image: np.ndarray, t: float) -> None:
        """A frame the camera delivered (read at host time `t`): its working image joins the queue."""
        offered = time.monotonic()
        work = self.track.prepare(image)
        with self._cond:
            self._stats["frames_offered"] += 1
            if len(self._frames) >= QUEUE_FRAMES:
                self._frames.popleft()
                self._stats["frames_skipped"] += 1
            self._frames.append((work, float(t), offered))
            self._cond.notify()

    def poll(self, timeout: float) -> GyroBatch | None:
        with self._cond:
            if not self._frames:
                self._cond.wait(timeout)
            if not self._frames:
                return None
            work, t, offered = self._frames.popleft()
        s = self.track.push_working(work, t)
        with self._cond:
            self._delays.append(time.monotonic() - offered)
        if s is None:
            return None
        batch = GyroBatch(s.t, s.rate, self._seq, gap_before=s.gap_before)
        self._seq += len(s.t)
        return self._count_batch(batch)

    def stats(self) -> dict:
        out = super().stats()
        out.update(self.track.counts, motion_source=self.motion_source,
                   sigma_rad_s=self.track.last_sigma_rad_s, overlay_fraction=self.track.overlay.fraction)
        with self._cond:
            d = np.array(self._delays) * 1e3
        if len(d):
            # from a frame's offer to its pair registered (the samples go out then): what the frame
            # before it waits beyond a period
            out.update(register_delay_ms_p50=float(np.percentile(d, 50)),
                       register_delay_ms_p99=float(np.percentile(d, 99)))
        return out


__all__ = ["VideoGyro"]
