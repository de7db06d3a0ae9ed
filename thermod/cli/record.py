"""`thermod record`: subscribe to ``raw``, ``gyro`` and ``health`` and write a format-v1 recording.

The daemon must publish raw frames (``[publish] raw = true``). Frames go to disk as they arrive
(``<output>.part``, so memory stays flat however long the recording), and the file is renamed into
place when it is complete. Frames end up in time order; gyro samples are kept as received, gaps
included (never interpolated): ``record/gyro_seq`` holds each sample's device index (a jump = lost
samples) and ``record/gyro_gap_before`` marks samples the driver flagged as following a loss;
``record/frame_id`` the camera frame numbers, whose jumps ``record.attrs`` splits into
``lost_raw_messages`` (lost on the way) and ``camera_frames_lost`` (never sent: the camera lost
them, as the daemon said in the next frame). The calibration comes from ``--config``, else from
the daemon's ``health`` messages, else defaults sized to the frames (``record.attrs`` says which).
Whatever stops the recording — time up, Ctrl-C, SIGTERM, an error — what was received is written;
if the recording cannot be completed, the ``.part`` file keeps the data and the error names it.
"""

from __future__ import annotations

import collections
import logging
import signal
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from thermod.client.subscriber import Subscriber
from thermod.errors import RecordingError, ThermodError
from thermod.io import recording
from thermod.io.endpoints import DEFAULT_ENDPOINT
from thermod.physics.calibration import Calibration

log = logging.getLogger(__name__)


def add_arguments(p) -> None:
    p.add_argument("-o", "--output", required=True, help="recording to write: HDF5 format v1, or ROS 2 "
                   "messages with deblurred frames too if it ends in .mcap (thermod.io.mcap)")
    p.add_argument("--seconds", type=float, default=None, help="stop after N seconds (default: Ctrl-C)")
    p.add_argument("--endpoint", default=DEFAULT_ENDPOINT, help="publisher address (default %(default)s)")
    p.add_argument("--config", default=None, help="take the calibration from this thermod.toml")
    p.add_argument("--curve-server-key", default=None, help="publisher's public certificate → CURVE")
    p.add_argument("--curve-client-key", default=None, help="this client's *.key_secret certificate")


class RecordWriter:
    """Streams received messages into ``<path>.part`` (through `thermod.io.recording.Writer`, the
    one writer of format v1); `finish()` completes the file.

    Frames are appended to disk one chunk each; gyro samples (20 bytes each) stay in memory until
    `finish`. Frames of another size than the first one are dropped and counted.
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
        self.calibration: dict | None = None
        self.health = 0
        self._flush_s, self._last_flush = flush_s, time.monotonic()

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
        now = time.monotonic()
        if now - self._last_flush > self._flush_s:  # a crash then loses at most ~1 s
            self._w.flush()
            self._last_flush = now

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
            for name, data in zip(("gyro/t", "gyro/rate", "record/gyro_seq", "record/gyro_gap_before"),
                                  self._gyro(), strict=True):
                w.put(name, data)
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


def record(sub: Subscriber, seconds: float | None, writer: RecordWriter, stop=lambda: False,
           counts: dict | None = None) -> RecordWriter:
    """Receive into `writer` until `seconds` pass, `stop()` is true or Ctrl-C. `counts`, if given,
    gets ``camera_frames_lost``: the frames the camera lost between two raw frames received (each raw
    header's ``gap_before``, the first one's left out), which skip frame ids without a message lost."""
    t_end = None if seconds is None else time.monotonic() + seconds
    counts = {} if counts is None else counts
    counts.setdefault("camera_frames_lost", 0)
    first_raw = True
    try:
        while not stop() and (t_end is None or time.monotonic() < t_end):
            msg = sub.recv(0.2 if t_end is None else min(0.2, max(0.0, t_end - time.monotonic())))
            if msg is not None:
                if msg[0] == "raw":
                    gap = msg[1].get("gap_before", 0)
                    if not first_raw and isinstance(gap, int) and gap > 0:
                        counts["camera_frames_lost"] += gap
                    first_raw = False
                writer.add(*msg)
    except KeyboardInterrupt:
        log.info("interrupted: writing what was received")
    return writer


def run(args) -> int:
    calibration = None
    if args.config:
        from thermod.runtime import config

        calibration = config.load(args.config, check_devices=False).calibration
    out = Path(args.output)
    if not out.parent.is_dir():
        raise RecordingError(out, "file", f"directory {out.parent} does not exist")
    # SIGTERM and Ctrl-C end the loop between two messages: a KeyboardInterrupt raised inside an append
    # would leave a frame without its time and the whole recording refused
    stopping = []
    previous = {}
    for sig in (signal.SIGTERM, signal.SIGINT):
        try:
            previous[sig] = signal.signal(sig, lambda *_: stopping.append(True))
        except ValueError:  # not the main thread: Ctrl-C/--seconds still work
            pass
    started = time.monotonic()
    attrs = {"endpoint": args.endpoint}
    as_mcap = out.suffix.lower() == ".mcap"
    if as_mcap:
        from thermod.io.mcap import McapRecordWriter
    writer = McapRecordWriter(out) if as_mcap else RecordWriter(out)
    try:
        # A deep receive queue: a recorder must ride out disk stalls without losing messages.
        topics = ("raw", "gyro", "health") + (("frame",) if as_mcap else ())
        with Subscriber(args.endpoint, topics, curve_server_key=args.curve_server_key,
                        curve_client_key_file=args.curve_client_key, rcvhwm=10000) as sub:
            counts: dict = {}
            try:
                record(sub, args.seconds, writer, stop=lambda: bool(stopping), counts=counts)
            finally:
                attrs.update(counts)
                attrs.update(seconds=time.monotonic() - started, lost_raw_messages=sub.gaps.get("raw", 0),
                             lost_gyro_messages=sub.gaps.get("gyro", 0),
                             rejected_messages=sum(sub.errors.values()))
    finally:
        try:
            if writer.empty:
                writer.discard()
            else:  # also after an error: what was received is written
                writer.finish(calibration, attrs)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    if writer.empty:
        raise ThermodError(f"nothing received from {args.endpoint} (raw/gyro); is `thermod run` up?")
    if as_mcap:
        print(f"wrote {out}: messages by topic {writer.counts}, calibration from {writer.source}")
        return 0
    with h5py.File(out, "r") as f:
        n, shape, m = f["camera/t"].shape[0], f["camera/frames"].shape[1:], f["gyro/t"].shape[0]
        gt = f["gyro/t"][()]
        seq = f["record/gyro_seq"][()]
        source = f["record"].attrs["calibration_source"]
    rate = (m - 1) / (gt[-1] - gt[0]) if m > 1 else float("nan")
    lost = int(np.sum(np.maximum(np.diff(seq) - 1, 0))) if m > 1 else 0
    print(f"wrote {out}: {n} frames {shape}, {m} gyro samples ({rate:.1f} Hz, {lost} lost in gaps), "
          f"lost messages raw {attrs['lost_raw_messages']} gyro {attrs['lost_gyro_messages']}, "
          f"camera frames lost by the camera {attrs['camera_frames_lost']}, "
          f"calibration from {source}")
    if n == 0:
        print("note: no raw frames: the daemon publishes them only with [publish] raw = true",
              file=sys.stderr)
    return 0
