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
Whatever stops the recording — time up, Ctrl-C, SIGTERM, an error, the daemon gone (nothing for
``--timeout`` s and nothing listening at the endpoint: exit 1, as `thermod watch`) — what was received
is written; if the recording cannot be completed, the ``.part`` file keeps the data and the error
names it.
"""

from __future__ import annotations

import logging
import math
import signal
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from thermod.client.subscriber import SILENCE_S, Silence, Subscriber, gone_message
from thermod.errors import RecordingError, ThermodError
from thermod.io.endpoints import DEFAULT_ENDPOINT
from thermod.io.stream_recording import RecordWriter

log = logging.getLogger(__name__)


def add_arguments(p) -> None:
    p.add_argument("-o", "--output", required=True, help="recording to write: HDF5 format v1, or ROS 2 "
                   "messages with deblurred frames too if it ends in .mcap (thermod.io.mcap)")
    p.add_argument("--seconds", type=float, default=None, help="stop after N seconds (default: Ctrl-C)")
    p.add_argument("--endpoint", default=DEFAULT_ENDPOINT, help="publisher address (default %(default)s)")
    p.add_argument("--timeout", type=float, default=SILENCE_S, help=Silence.OPTION_HELP)
    p.add_argument("--config", default=None, help="take the calibration from this thermod.toml")
    p.add_argument("--curve-server-key", default=None, help="publisher's public certificate → CURVE")
    p.add_argument("--curve-client-key", default=None, help="this client's *.key_secret certificate")


def record(sub: Subscriber, seconds: float | None, writer: RecordWriter, stop=lambda: False,
           counts: dict | None = None, drain_s: float = 1.0, silence: Silence | None = None) -> RecordWriter:
    """Receive into `writer` until `seconds` pass, `stop()` is true, Ctrl-C, or `silence` finds the
    publisher gone (`Silence`; ``silence.silent_s`` set). `counts`, if given, gets
    ``camera_frames_lost``: the frames the camera lost between two raw frames received (each raw
    header's ``gap_before``, the first one's left out), which skip frame ids without a message lost.

    Gyro samples travel in batches that can trail the frames they cover, so when `seconds` pass the
    recorder takes no more frames but keeps the gyro coming, for at most `drain_s`, until it reaches
    the last frame kept: every frame recorded has the motion that blurred it."""
    t_end = None if seconds is None else time.monotonic() + seconds
    counts = {} if counts is None else counts
    counts.setdefault("camera_frames_lost", 0)
    first_raw = True
    newest = {"raw": -np.inf, "gyro": -np.inf}      # the newest frame time and gyro sample time kept

    def take(msg) -> None:
        nonlocal first_raw
        topic, header, array = msg
        if topic == "raw":
            gap = header.get("gap_before", 0)
            if not first_raw and isinstance(gap, int) and gap > 0:
                counts["camera_frames_lost"] += gap
            first_raw = False
        if topic in newest:
            newest[topic] = max(newest[topic], _newest(header.get("t") if topic == "raw" else array["t"]))
        writer.add(*msg)

    try:
        while not stop() and (t_end is None or time.monotonic() < t_end):
            until = min(math.inf if t_end is None else t_end, math.inf if silence is None else silence.due)
            msg = sub.recv(max(0.0, min(0.2, until - time.monotonic())))
            if msg is not None:
                take(msg)
                if silence is not None:
                    silence.heard()
            elif silence is not None and silence.gone():
                return writer            # no gyro batch will trail the last frame either
            else:
                writer.tick()            # what came before a pause reaches the file within ~1 s
        drain_end = time.monotonic() + drain_s
        while newest["gyro"] < newest["raw"] and (now := time.monotonic()) < drain_end:
            msg = sub.recv(min(0.2, drain_end - now))
            if msg is not None and msg[0] != "raw":
                take(msg)
    except KeyboardInterrupt:
        log.info("interrupted: writing what was received")
    return writer


def _newest(t) -> float:
    """The latest finite time among `t` (a header's time or a batch's times); -inf when there is none."""
    try:
        t = np.asarray(t, float).ravel()
    except (TypeError, ValueError):
        return -np.inf
    t = t[np.isfinite(t)]
    return float(t.max()) if t.size else -np.inf


def run(args) -> int:
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise RecordingError(Path(args.output), "--seconds",
                             f"expected a finite number > 0, got {args.seconds}")
    if not (math.isfinite(args.timeout) and args.timeout >= 0):
        raise RecordingError(Path(args.output), "--timeout",
                             f"expected a finite number ≥ 0, got {args.timeout}")
    calibration = None
    if args.config:
        from thermod.runtime import config

        calibration = config.load(args.config, check_devices=False).calibration
    out = Path(args.output)
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
    silence = Silence(args.endpoint, args.timeout)
    as_mcap = out.suffix.lower() == ".mcap"
    if as_mcap:
        from thermod.io.mcap import McapRecordWriter
    # the calibration goes into an MCAP file as soon as it is known: a killed recorder's .part has it
    writer = McapRecordWriter(out, calibration) if as_mcap else RecordWriter(out)
    try:
        # A deep receive queue: a recorder must ride out disk stalls without losing messages.
        topics = ("raw", "gyro", "health") + (("frame",) if as_mcap else ())
        with Subscriber(args.endpoint, topics, curve_server_key=args.curve_server_key,
                        curve_client_key_file=args.curve_client_key, rcvhwm=10000) as sub:
            counts: dict = {}
            try:
                record(sub, args.seconds, writer, stop=lambda: bool(stopping), counts=counts, silence=silence)
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
    # the daemon gone: what it sent is written above, and the exit status says the recording ended early
    gone = None if silence.silent_s is None else gone_message("record", args.endpoint, silence.silent_s,
                                                              received=not writer.empty)
    if writer.empty and gone is None:
        raise ThermodError(f"nothing received from {args.endpoint} (raw/gyro); is `thermod run` up?")
    if not writer.empty and as_mcap:
        print(f"wrote {out}: messages by topic {writer.counts}, calibration from {writer.source}")
    elif not writer.empty:
        _summary(out, attrs)
    if gone is not None:
        print(gone, file=sys.stderr)
        return 1
    return 0


def _summary(out: Path, attrs: dict) -> None:
    """Print what the recording `out` holds (format v1)."""
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
