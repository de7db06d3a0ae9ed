"""`thermod record`: subscribe to ``raw``, ``gyro`` and ``health`` and write a format-v1 recording.

The daemon must publish raw frames (``[publish] raw = true``). Frames are written in time order;
gyro samples are written as received, gaps included (never interpolated): ``record/gyro_seq`` holds
each sample's device index (a jump = lost samples) and ``record/gyro_gap_before`` marks samples the
driver flagged as following a loss. The calibration comes from ``--config``, else from the daemon's
``health`` messages, else defaults sized to the frames (flagged in ``record.attrs``).
Whatever stops the recording — time up, Ctrl-C, SIGTERM, an error — what was received is written;
if even that fails, the arrays go to ``<output>.rescue.npz``.
"""

from __future__ import annotations

import collections
import json
import logging
import signal
import sys
import time
from pathlib import Path

import numpy as np

from thermod import recording
from thermod.calibration import Calibration
from thermod.errors import RecordingError, ThermodError
from thermod.publish import DEFAULT_ENDPOINT, Subscriber

log = logging.getLogger(__name__)


def add_arguments(p) -> None:
    p.add_argument("-o", "--output", required=True, help="recording to write (HDF5, format v1)")
    p.add_argument("--seconds", type=float, default=None, help="stop after N seconds (default: Ctrl-C)")
    p.add_argument("--endpoint", default=DEFAULT_ENDPOINT, help="publisher address (default %(default)s)")
    p.add_argument("--config", default=None, help="take the calibration from this thermod.toml")
    p.add_argument("--curve-server-key", default=None, help="publisher's public certificate → CURVE")
    p.add_argument("--curve-client-key", default=None, help="this client's *.key_secret certificate")


class RecordBuilder:
    """Collects received messages; `build()` turns them into a `recording.Recording`."""

    def __init__(self):
        self.frames: list[np.ndarray] = []
        self.frame_t: list[float] = []
        self.frame_id: list[int] = []
        self.gyro_t: list[np.ndarray] = []
        self.gyro_rate: list[np.ndarray] = []
        self.gyro_seq: list[np.ndarray] = []
        self.gyro_gap: list[np.ndarray] = []
        self.calibration: dict | None = None
        self.health = 0

    @property
    def empty(self) -> bool:
        return not self.frames and not self.gyro_t

    def add(self, topic: str, header: dict, array: np.ndarray) -> None:
        if topic == "raw":
            self.frames.append(array)  # a read-only view that keeps its ZeroMQ message alive; no copy
            self.frame_t.append(float(header["t"]))
            self.frame_id.append(int(header.get("frame_id", -1)))
        elif topic == "gyro":
            n = len(array)
            self.gyro_t.append(array["t"])
            self.gyro_rate.append(array["rate"])
            self.gyro_seq.append(int(header.get("sample_seq", -1)) + np.arange(n, dtype=np.int64))
            gap = np.zeros(n, bool)
            gap[:1] = bool(header.get("gap_before"))
            self.gyro_gap.append(gap)
        elif topic == "health":
            self.health += 1
            if isinstance(header.get("calibration"), dict):
                self.calibration = header["calibration"]

    def build(self, calibration: Calibration | None = None, attrs: dict | None = None) -> recording.Recording:
        """Frames sorted by time (duplicates and off-size frames dropped with a warning), gyro samples
        sorted by time with duplicates (same time) dropped; calibration: argument > health > defaults."""
        source = "config"
        if calibration is None and self.calibration is not None:
            try:
                calibration, source = Calibration.from_dict(self.calibration), "health"
            except (TypeError, ValueError) as e:
                log.warning("calibration in the health messages is unusable (%s); using defaults", e)
        frames, t, fid, dropped = self._frames()
        if calibration is None:
            h, w = frames.shape[1:] if len(frames) else (Calibration().height, Calibration().width)
            calibration = Calibration(width=w, height=h, cx=(w - 1) / 2, cy=(h - 1) / 2)
            source = "defaults"
            log.warning("no calibration received (no health messages) nor --config: writing defaults "
                        "for a %dx%d camera; fix them before deblurring", w, h)
        if not len(frames):
            frames = np.zeros((0, calibration.height, calibration.width), np.uint16)
        gt, grate, gseq, ggap = self._gyro()
        extra_attrs = {"record": {**(attrs or {}), "calibration_source": source,
                                  "frames_dropped": dropped}}
        extras = {"record/frame_id": fid, "record/gyro_seq": gseq, "record/gyro_gap_before": ggap}
        return recording.Recording(frames, t, gt, grate, calibration, extras=extras, extra_attrs=extra_attrs)

    def _frames(self):
        if not self.frames:
            return np.zeros((0, 0, 0), np.uint16), np.zeros(0), np.zeros(0, np.int64), 0
        shapes = collections.Counter(f.shape for f in self.frames)
        shape = shapes.most_common(1)[0][0]
        t = np.asarray(self.frame_t)
        order = np.argsort(t, kind="stable")
        keep, last, dropped = [], -np.inf, 0
        for i in order:
            if self.frames[i].shape != shape or self.frames[i].dtype != np.uint16 or not t[i] > last:
                dropped += 1
                continue
            keep.append(i)
            last = t[i]
        if dropped:
            log.warning("dropped %d raw frames (repeated time stamp or a size other than %s)", dropped, shape)
        frames = np.empty((len(keep), *shape), np.uint16)
        for j, i in enumerate(keep):
            frames[j] = self.frames[i]
        return frames, t[keep], np.asarray(self.frame_id, np.int64)[keep], dropped

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

    def rescue(self, path: Path) -> Path:
        """Last resort when a recording cannot be built/written: the raw arrays as .npz (no pickle)."""
        out = path.with_name(path.name + ".rescue.npz")
        shapes = {f.shape for f in self.frames}
        frames = np.stack(self.frames) if len(shapes) == 1 else np.zeros((0,), np.uint16)
        np.savez(out, frames=frames, t=np.asarray(self.frame_t), frame_id=np.asarray(self.frame_id),
                 gyro_t=np.concatenate(self.gyro_t) if self.gyro_t else np.zeros(0),
                 gyro_rate=np.concatenate(self.gyro_rate) if self.gyro_rate else np.zeros((0, 3), np.float32),
                 gyro_seq=np.concatenate(self.gyro_seq) if self.gyro_seq else np.zeros(0, np.int64),
                 calibration=np.asarray(json.dumps(self.calibration)))
        return out


def record(sub: Subscriber, seconds: float | None, builder: RecordBuilder | None = None,
           stop=lambda: False) -> RecordBuilder:
    """Receive into `builder` until `seconds` pass, `stop()` is true or Ctrl-C."""
    builder = builder or RecordBuilder()
    t_end = None if seconds is None else time.monotonic() + seconds
    try:
        while not stop() and (t_end is None or time.monotonic() < t_end):
            msg = sub.recv(0.2 if t_end is None else min(0.2, max(0.0, t_end - time.monotonic())))
            if msg is not None:
                builder.add(*msg)
    except KeyboardInterrupt:
        log.info("interrupted: writing what was received")
    return builder


def save(builder: RecordBuilder, path, calibration: Calibration | None = None, attrs: dict | None = None):
    """Build and write the recording; on failure write the rescue file and re-raise with its name."""
    path = Path(path)
    try:
        rec = builder.build(calibration, attrs)
        recording.write(path, rec)
        return rec
    except (ThermodError, OSError, ValueError) as e:
        rescue = builder.rescue(path)
        raise RecordingError(path, "file", f"could not write the recording ({e}); the received data "
                             f"is in {rescue}") from None


def run(args) -> int:
    calibration = None
    if args.config:
        from thermod import config

        calibration = config.load(args.config, check_devices=False).calibration
    out = Path(args.output)
    if not out.parent.is_dir():
        raise RecordingError(out, "file", f"directory {out.parent} does not exist")
    stopping = []
    previous = None
    try:
        previous = signal.signal(signal.SIGTERM, lambda *_: stopping.append(True))
    except ValueError:  # not the main thread: Ctrl-C/--seconds still work
        pass
    started = time.monotonic()
    try:
        with Subscriber(args.endpoint, ("raw", "gyro", "health"), curve_server_key=args.curve_server_key,
                        curve_client_key_file=args.curve_client_key) as sub:
            builder = RecordBuilder()
            try:
                record(sub, args.seconds, builder, stop=lambda: bool(stopping))
            finally:
                gaps, rejected = dict(sub.gaps), sum(sub.errors.values())
                attrs = {"endpoint": args.endpoint, "seconds": time.monotonic() - started,
                         "lost_raw_messages": gaps.get("raw", 0), "lost_gyro_messages": gaps.get("gyro", 0),
                         "rejected_messages": rejected}
                if not builder.empty:
                    rec = save(builder, out, calibration, attrs)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if builder.empty:
        raise ThermodError(f"nothing received from {args.endpoint} (raw/gyro); is `thermod run` up?")
    n, m = rec.n_frames, len(rec.gyro_t)
    rate = (m - 1) / (rec.gyro_t[-1] - rec.gyro_t[0]) if m > 1 else float("nan")
    lost = int(np.sum(np.maximum(np.diff(rec.extras["record/gyro_seq"]) - 1, 0))) if m > 1 else 0
    print(f"wrote {out}: {n} frames {rec.frames.shape[1:]}, {m} gyro samples ({rate:.1f} Hz, {lost} lost "
          f"in gaps), lost messages raw {attrs['lost_raw_messages']} gyro {attrs['lost_gyro_messages']}, "
          f"calibration from {rec.extra_attrs['record']['calibration_source']}")
    if n == 0:
        print("note: no raw frames: the daemon publishes them only with [publish] raw = true",
              file=sys.stderr)
    return 0
