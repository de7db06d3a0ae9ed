"""A format-v1 recording written from a stream of wire messages as they arrive (`RecordWriter`):
``raw`` frames go to disk one chunk each (``<path>.part``, so memory stays flat), ``gyro`` batches
about every second, and `finish` completes the file (the gyro in time order, the calibration of the
``health`` messages) and renames it into place. Whatever fails, the ``.part`` file keeps every frame
and gyro sample received (a killed recorder: all but the last second's) and the error names it.
`thermod record` (a live stream) and the bag ingest (`thermod.ingest.bag`) write with it.
"""

from __future__ import annotations

import collections
import logging
import time
from pathlib import Path

import numpy as np

from thermod.errors import RecordingError, ThermodError
from thermod.io import recording
from thermod.physics.calibration import Calibration

log = logging.getLogger(__name__)


class RecordWriter:
    """Streams received messages into ``<path>.part`` (through `thermod.io.recording.Writer`, the
    one writer of format v1); `finish()` completes the file.

    Frames are appended to disk one chunk each; gyro batches at each flush (they also stay in memory,
    20 bytes a sample, to be put in time order at `finish`). Frames of another size than the first
    one are dropped and counted.
    """

    def __init__(self, path, flush_s: float = 1.0):
        self.path = Path(path)
        self._w = recording.Writer(self.path)
        self.spool = self._w.part
        self._shape: tuple[int, int] | None = None
        self.n_frames = 0
        self.dropped = collections.Counter()
        self.gyro_t: list[np.ndarray] = []
        self.gyro_rate: list[np.ndarray] = []
        self.gyro_seq: list[np.ndarray] = []
        self.gyro_gap: list[np.ndarray] = []
        self._spooled = 0          # gyro batches on disk already
        self.calibration: dict | None = None
        self.health = 0
        self.written = {"frames": 0, "gyro": 0}     # what `finish` put in the file
        self._flush_s, self._last_flush = flush_s, time.monotonic()

    @property
    def frame_shape(self) -> tuple[int, int] | None:
        """(height, width) of the frames kept (the first one's), None before any."""
        return self._shape

    @property
    def empty(self) -> bool:
        return self.n_frames == 0 and not self.gyro_t

    def add(self, topic: str, header: dict, array: np.ndarray) -> None:
        if topic == "raw":
            self._add_frame(array, float(header["t"]), int(header.get("frame_id", -1)))
        elif topic == "gyro":
            n = len(array)
            self.gyro_t.append(np.array(array["t"]))
            self.gyro_rate.append(np.array(array["rate"]))
            self.gyro_seq.append(int(header.get("sample_seq", -1)) + np.arange(n, dtype=np.int64))
            gap = np.zeros(n, bool)
            gap[:1] = bool(header.get("gap_before"))
            self.gyro_gap.append(gap)
        elif topic == "health":
            self.health += 1
            if isinstance(header.get("calibration"), dict):
                self.calibration = header["calibration"]
        self.tick()

    def tick(self) -> None:
        """Flush (gyro batches included) if `flush_s` have passed since the last time: a crash then
        loses at most ~1 s. Called after each message and while nothing arrives."""
        now = time.monotonic()
        if now - self._last_flush > self._flush_s:
            self._spool_gyro()
            self._w.flush()
            self._last_flush = now

    def _spool_gyro(self) -> None:
        """The gyro batches received since the last flush, appended to the ``.part`` file."""
        k = self._spooled
        if k < len(self.gyro_t):
            w = self._w
            w.extend("gyro/t", np.concatenate(self.gyro_t[k:]), np.float64)
            w.extend("gyro/rate", np.concatenate(self.gyro_rate[k:]), np.float32)
            w.extend("record/gyro_seq", np.concatenate(self.gyro_seq[k:]), np.int64)
            w.extend("record/gyro_gap_before", np.concatenate(self.gyro_gap[k:]), bool)
            self._spooled = len(self.gyro_t)

    def _add_frame(self, image: np.ndarray, t: float, frame_id: int) -> None:
        if image.ndim != 2 or image.dtype != np.uint16:
            self.dropped["not uint16 [H, W]" if self._shape is None else "size changed"] += 1
            return
        if self._shape is None:
            self._shape = image.shape
        if image.shape != self._shape:
            self.dropped["size changed"] += 1
            return
        if not np.isfinite(t):
            self.dropped["non-finite time"] += 1
            return
        self._w.append_frame(image, t)
        self._w.append("record/frame_id", frame_id, np.int64)
        self.n_frames += 1

    # ---------------------------------------------------------------------------------- finish
    def finish(self, calibration: Calibration | None = None, attrs: dict | None = None) -> Path:
        """Complete the file: gyro data, calibration attributes, frames in time order; rename into
        place. Calibration: argument > health > defaults sized to the frames. On failure the
        ``.part`` file keeps every received frame and gyro sample and the error names it."""
        w = self._w
        try:
            gyro = self._gyro()
            for name, data in zip(("gyro/t", "gyro/rate", "record/gyro_seq", "record/gyro_gap_before"),
                                  gyro, strict=True):
                w.rewrite(name, data)           # in time order, repeats and non-finite samples out
            calibration, source = self._calibration(calibration)
            if self._shape is None:
                w.put("record/frame_id", np.zeros(0, np.int64))
            dup = w.sort_frames()
            if dup:
                log.warning("dropping %d raw frames with a repeated time stamp", dup)
            w.set_attrs("record", {**(attrs or {}), "calibration_source": source,
                                   "health_messages": self.health,
                                   "frames_dropped": sum(self.dropped.values()) + dup})
            w.commit(calibration)
            self.written = {"frames": self.n_frames - dup, "gyro": len(gyro[0])}
        except (OSError, ValueError, KeyError, TypeError) as e:
            w.abort(keep=True)
            raise RecordingError(self.path, "file", f"could not complete the recording ({e}); the received "
                                 f"data is in {self.spool}") from None
        except RecordingError as e:
            w.abort(keep=True)
            raise RecordingError(self.path, e.field, f"{e.problem}; the received data is in "
                                 f"{self.spool}") from None
        return self.path

    def _calibration(self, calibration):
        if calibration is not None:
            return calibration, "config"
        if self.calibration is not None:
            try:
                return Calibration.from_dict(self.calibration), "health"
            except (TypeError, ValueError, KeyError, ThermodError) as e:
                log.warning("calibration in the health messages is unusable (%s); using defaults", e)
        h, w = self._shape if self._shape is not None else (Calibration().height, Calibration().width)
        log.warning("no calibration received (no health messages) nor --config: writing defaults for a "
                    "%dx%d camera; fix them before deblurring", w, h)
        return Calibration(width=w, height=h, cx=(w - 1) / 2, cy=(h - 1) / 2), "defaults"

    def _gyro(self):
        if not self.gyro_t:
            return np.zeros(0), np.zeros((0, 3), np.float32), np.zeros(0, np.int64), np.zeros(0, bool)
        t = np.concatenate(self.gyro_t)
        rate = np.concatenate(self.gyro_rate).astype(np.float32)
        seq = np.concatenate(self.gyro_seq)
        gap = np.concatenate(self.gyro_gap)
        order = np.argsort(t, kind="stable")
        t, rate, seq, gap = t[order], rate[order], seq[order], gap[order]
        # A sample received twice (same time) is kept once; real losses stay visible in `seq`.
        keep = np.ones(len(t), bool)
        keep[1:] = np.diff(t) > 0
        keep &= np.isfinite(t) & np.all(np.isfinite(rate), axis=1)
        if not keep.all():
            log.warning("dropped %d gyro samples (repeated time stamp or non-finite)", int((~keep).sum()))
        return t[keep], rate[keep], seq[keep], gap[keep]

    def close(self) -> None:
        """Close the spool without completing it (the data stays in ``.part``)."""
        self._w.abort(keep=True)

    def discard(self) -> None:
        self._w.abort()
