"""Recordings as ROS 2 messages in MCAP, and ROS bags (MCAP, rosbag2, ROS 1) read back as messages.

Written (`McapWriter`, CDR through ``mcap-ros2-support``; docs/design.md §3 "MCAP"):

- ``/thermal/image_raw``, Image 16UC1: camera frames, raw counts; ``/thermal/image_deblurred``,
  Image 32FC1: thermod's output frames (deblurred or passed through), in the raw frames' counts;
- ``/thermal/camera_info``, CameraInfo: K from fx, fy, cx, cy, no distortion, one per raw frame;
- ``/imu/data``, sensor_msgs/msg/Imu: raw gyro samples (gyro frame, rad/s), no orientation.

Header stamps and log times are the recording's times: host ``CLOCK_MONOTONIC`` seconds as mapped
by thermod (frames: when the last row was read; gyro: the gyro's mapped clock, *before*
``time_offset_s``), not UNIX time. The whole thermod calibration travels in the MCAP metadata
record ``thermod`` (key ``calibration``, JSON), so `thermod import` restores it exactly. The
recorder (`McapRecordWriter`) writes that record as soon as it knows the calibration, again at each
change, and a last time with its attributes at the end; it ends a chunk at least every second, so a
killed recorder's ``.part`` holds its calibration and all but about the last second.

Read (`Bag`): a ``.mcap`` file through ``mcap`` + ``mcap_ros2``; a rosbag2 directory or a ROS 1
``.bag`` through ``rosbags``. Messages are streamed in log-time order, never loaded all at once. An
MCAP file without its summary — the ``.mcap.part`` a killed `thermod record` leaves, cut anywhere —
is read from the start instead, in file order, up to its last complete message.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import time
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from thermod.errors import RecordingError
from thermod.paths import output_problem
from thermod.physics.calibration import Calibration

log = logging.getLogger(__name__)

RAW_TOPIC = "/thermal/image_raw"
DEBLURRED_TOPIC = "/thermal/image_deblurred"
CAMERA_INFO_TOPIC = "/thermal/camera_info"
IMU_TOPIC = "/imu/data"
CAMERA_FRAME_ID = "thermal_camera"
GYRO_FRAME_ID = "thermal_gyro"
METADATA_NAME = "thermod"

IMAGE = "sensor_msgs/msg/Image"
IMU = "sensor_msgs/msg/Imu"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

# ROS 2 (Humble and later) definitions in the concatenated form ros2 bag and Foxglove expect:
# the type's fields, then each dependency after a separator line and "MSG: pkg/Type".
_SEP = "=" * 80 + "\n"
_HEADER = (
    "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    + _SEP
    + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)
MSGDEFS = {
    IMAGE: (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
        "uint32 step\nuint8[] data\n" + _SEP + _HEADER
    ),
    IMU: (
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"
        + _SEP
        + _HEADER
        + _SEP
        + "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\n"
        "float64 w\n" + _SEP + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
    ),
    CAMERA_INFO: (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
        "uint32 binning_y\nsensor_msgs/RegionOfInterest roi\n"
        + _SEP
        + _HEADER
        + _SEP
        + "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\n"
        "uint32 width\nbool do_rectify\n"
    ),
}

# Imu: orientation_covariance[0] = -1 says "no orientation estimate"; the other covariances are
# unknown (all zero, the ROS convention); linear acceleration is not measured (-1 as well).
_NO_ESTIMATE = [-1.0] + [0.0] * 8
_UNKNOWN = [0.0] * 9


def stamp(t: float, path="<mcap>", what="stamp") -> dict:
    """Seconds → builtin_interfaces/Time. MCAP log times are unsigned: negative times are refused."""
    ns = to_ns(t, path, what)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def to_ns(t: float, path="<mcap>", what="time") -> int:
    if not np.isfinite(t) or t < 0:
        raise RecordingError(path, what, f"time {t!r} s cannot be an MCAP log time (finite, ≥ 0 expected)")
    return int(round(float(t) * 1e9))


def from_stamp(s) -> float:
    return int(s.sec) + int(s.nanosec) * 1e-9


# ----------------------------------------------------------------------------------------- writing
def imu_cdr_dtype(frame_id: str) -> np.dtype:
    """The CDR (little-endian) layout of a sensor_msgs/msg/Imu with this header frame_id: a fixed
    record, so a batch of samples is packed by numpy instead of field by field (the generic
    encoder costs ~0.3 ms per message, too slow for a 1 kHz gyro). Alignment is counted from
    after the 4-byte encapsulation header; float64 fields align to 8."""
    n = len(frame_id.encode()) + 1  # CDR strings: uint32 length including the NUL, then the bytes
    pad = -(12 + n) % 8
    f8 = "<f8"
    return np.dtype([("encapsulation", ">u4"), ("sec", "<i4"), ("nanosec", "<u4"), ("frame_id_len", "<u4"),
                     ("frame_id", f"S{n + pad}"), ("orientation", f8, 4), ("orientation_covariance", f8, 9),
                     ("angular_velocity", f8, 3), ("angular_velocity_covariance", f8, 9),
                     ("linear_acceleration", f8, 3), ("linear_acceleration_covariance", f8, 9)])


CDR_LE = 0x00010000  # encapsulation header, big-endian u4 → bytes 00 01 00 00: plain CDR, little-endian
_IMU_CDR = imu_cdr_dtype(GYRO_FRAME_ID)


class McapWriter:
    """A ROS 2 MCAP file (profile ``ros2``, CDR messages, ``ros2msg`` schemas) written into
    ``<path>.part`` and renamed into place by `commit`.

    The container is `mcap.writer.Writer`; Image and CameraInfo are encoded by mcap-ros2-support's
    encoder for `MSGDEFS`, Imu batches by `imu_cdr_dtype` (tests compare both byte for byte).
    `compress`: LZ4 chunks (exports); a live recorder writes them uncompressed, like the HDF5
    recorder, to keep up with 50 raw + 50 float frames/s (compression tripled the cost per frame)."""

    def __init__(self, path: str | os.PathLike, compress: bool = True):
        from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
        from mcap.writer import CompressionType, Writer
        from mcap_ros2 import __version__ as ros2_version
        from mcap_ros2._dynamic import serialize_dynamic

        self.path = Path(path)
        self.part = self.path.with_name(self.path.name + ".part")
        if (problem := output_problem(self.path)) is not None:
            raise RecordingError(self.path, "file", problem)
        try:
            self._file = open(self.part, "wb")  # noqa: SIM115 (closed by commit/abort)
        except OSError as e:
            raise RecordingError(self.path, "file", f"cannot create {self.part} ({e})") from None
        self._w = Writer(self._file, compression=CompressionType.LZ4 if compress else CompressionType.NONE)
        self._w.start(profile=Profile.ROS2, library=f"thermod, mcap-ros2-support {ros2_version}")
        self._encoders = {name: serialize_dynamic(name, text)[name] for name, text in MSGDEFS.items()}
        schemas = {name: self._w.register_schema(name, SchemaEncoding.ROS2, text.encode())
                   for name, text in MSGDEFS.items()}
        self._channels = {topic: self._w.register_channel(topic, MessageEncoding.CDR, schemas[msgtype])
                          for topic, msgtype in ((RAW_TOPIC, IMAGE), (DEBLURRED_TOPIC, IMAGE),
                                                 (CAMERA_INFO_TOPIC, CAMERA_INFO), (IMU_TOPIC, IMU))}
        self.counts = dict.fromkeys(self._channels, 0)

    def _add(self, topic: str, data: bytes, ns: int, seq: int) -> None:
        self._w.add_message(self._channels[topic], log_time=ns, data=data, publish_time=ns,
                            sequence=int(seq) & 0xFFFFFFFF)
        self.counts[topic] += 1

    def _write(self, topic: str, msgtype: str, msg: dict, ns: int, seq: int = 0) -> None:
        self._add(topic, self._encoders[msgtype](msg), ns, seq)

    def image(self, topic: str, image: np.ndarray, t: float, seq: int = 0) -> None:
        """A uint16 (16UC1) or float32 (32FC1) frame [H, W], little-endian."""
        kind = {np.dtype(np.uint16): "16UC1", np.dtype(np.float32): "32FC1"}.get(image.dtype)
        if kind is None or image.ndim != 2:
            raise RecordingError(
                self.path,
                topic,
                f"expected a uint16 or float32 [H, W] frame, got {image.dtype} {image.shape}",
            )
        h, w = image.shape
        data = np.ascontiguousarray(image, image.dtype.newbyteorder("<"))
        # The encoder writes the fields before `data`; `uint8[] data` is last, a uint32 count then
        # the bytes, so the frame is appended to that prefix in one copy (the encoder's byte stream
        # cost ~10 ms for a 640×480 float frame).
        head = self._encoders[IMAGE]({
            "header": {"stamp": stamp(t, self.path, topic), "frame_id": CAMERA_FRAME_ID},
            "height": h, "width": w, "encoding": kind, "is_bigendian": 0, "step": w * image.itemsize,
            "data": b""})
        self._add(topic, b"".join((head[:-4], struct.pack("<I", data.nbytes), data.data)),
                  to_ns(t, self.path, topic), seq)

    def raw(self, image: np.ndarray, t: float, frame_id: int = 0) -> None:
        self.image(RAW_TOPIC, np.asarray(image, np.uint16), t, frame_id)

    def deblurred(self, image: np.ndarray, t: float, frame_id: int = 0) -> None:
        self.image(DEBLURRED_TOPIC, np.asarray(image, np.float32), t, frame_id)

    def gyro(self, t: np.ndarray, rate: np.ndarray, first_seq: int = 0) -> None:
        """Raw gyro samples (mapped gyro clock s, gyro-frame rad/s [n, 3]), one Imu message each."""
        t = np.asarray(t, np.float64)
        rate = np.asarray(rate, np.float64).reshape(len(t), 3)
        ns = [to_ns(ti, self.path, IMU_TOPIC) for ti in t.tolist()]
        rec = np.zeros(len(t), _IMU_CDR)
        rec["encapsulation"] = CDR_LE
        rec["sec"], rec["nanosec"] = np.divmod(np.array(ns, np.int64), 1_000_000_000)
        rec["frame_id_len"] = len(GYRO_FRAME_ID) + 1
        rec["frame_id"] = GYRO_FRAME_ID.encode()
        rec["orientation"][:, 3] = 1.0
        rec["orientation_covariance"] = _NO_ESTIMATE
        rec["angular_velocity"] = rate
        rec["angular_velocity_covariance"] = _UNKNOWN
        rec["linear_acceleration_covariance"] = _NO_ESTIMATE
        for i, (n_i, r) in enumerate(zip(ns, rec, strict=True)):
            self._add(IMU_TOPIC, r.tobytes(), n_i, first_seq + i)

    def camera_info(self, calibration: Calibration, t: float, seq: int = 0) -> None:
        """The pinhole model of `calibration` (no distortion), stamped like the frame at `t`."""
        c = calibration
        self._write(
            CAMERA_INFO_TOPIC,
            CAMERA_INFO,
            {
                "header": {"stamp": stamp(t, self.path, CAMERA_INFO_TOPIC), "frame_id": CAMERA_FRAME_ID},
                "height": int(c.height),
                "width": int(c.width),
                "distortion_model": "plumb_bob",
                "d": [0.0] * 5,
                "k": [c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0],
                "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                "p": [c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
                "binning_x": 0,
                "binning_y": 0,
                "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
            },
            to_ns(t, self.path, CAMERA_INFO_TOPIC),
            seq,
        )

    def metadata(self, calibration: Calibration, attrs: dict | None = None) -> None:
        """The thermod calibration (JSON) and string attributes, in the metadata record ``thermod``."""
        data = {"calibration": json.dumps(calibration.as_dict())}
        data.update(
            {str(k): v if isinstance(v, str) else json.dumps(_plain(v)) for k, v in (attrs or {}).items()}
        )
        self._w.add_metadata(METADATA_NAME, data)

    def flush(self) -> None:
        """End the chunk being built, if it holds a message, and hand the file to the OS: a process
        killed afterwards leaves all of it in the ``.part`` file (no fsync: a power cut may not)."""
        try:
            self._w.flush()
        except (OSError, ValueError) as e:
            raise RecordingError(self.path, "file", f"cannot write {self.part} ({e})") from None

    def commit(self) -> Path:
        """Write the MCAP summary and rename the file into place."""
        try:
            self._w.finish()
            self._file.close()
            os.replace(self.part, self.path)
        except (OSError, ValueError) as e:
            self.abort(keep=True)
            raise RecordingError(
                self.path,
                "file",
                f"could not complete the MCAP file ({e}); what was written is in {self.part}",
            ) from None
        return self.path

    def abort(self, keep: bool = False) -> None:
        """Close without renaming; the ``.part`` file is removed unless `keep`."""
        if not self._file.closed:
            try:
                self._w.finish()  # an indexed, readable file even when stopped by an error
            except Exception:  # noqa: BLE001 - the file is being abandoned anyway
                pass
            self._file.close()
        if not keep:
            self.part.unlink(missing_ok=True)


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def export(recording_path: str | os.PathLike, out: str | os.PathLike) -> dict:
    """A format-v1 recording → MCAP (raw frames, deblurred frames if present, gyro, camera info,
    calibration metadata); frames are read one at a time. Returns the message counts per topic."""
    import h5py

    from thermod.io import recording

    recording_path = Path(recording_path)
    t, gyro_t, gyro_rate, calibration = recording.read_timeline(recording_path)
    w = McapWriter(out)
    try:
        with recording.open_file(recording_path) as f:
            frames = f["camera/frames"]
            fid = f["record/frame_id"][()] if "record/frame_id" in f else np.arange(len(t))
            deb = f["deblurred/frames"] if isinstance(f.get("deblurred/frames"), h5py.Dataset) else None
            deb_t = f["deblurred/t"][()] if deb is not None and "deblurred/t" in f else t
            for i, ti in enumerate(t.tolist()):
                w.raw(frames[i], ti, int(fid[i]))
                w.camera_info(calibration, ti, int(fid[i]))
                if deb is not None:
                    w.deblurred(deb[i], float(deb_t[i]), int(fid[i]))
        seq = np.arange(len(gyro_t))
        w.gyro(gyro_t, gyro_rate, int(seq[0]) if len(seq) else 0)
        w.metadata(calibration, {"source": str(recording_path)})
    except BaseException:
        w.abort()
        raise
    w.commit()
    return dict(w.counts)


class McapRecordWriter:
    """`thermod record` into MCAP: wire-v1 messages (``raw``, ``frame``, ``gyro``, ``health``)
    straight to disk, same interface as the HDF5 recorder (`add`, `tick`, `finish`, `discard`,
    `empty`), and what a kill loses is bounded:

    - the chunk being built is ended and the file flushed at least every `flush_s` (`tick`);
    - the calibration is written as soon as it is known — `calibration` (``--config``) at once, else
      each ``health`` message's that differs from the one in force (the first, then a SIGHUP reload
      or a monitor update) — as a ``thermod`` metadata record (``calibration``,
      ``calibration_source``, ``from_t``: the health message's time);
    - each raw frame gets a CameraInfo from the calibration in force when it arrives; frames received
      before any calibration get theirs when one comes, or at `finish` (defaults sized to the frames).

    `finish` writes the final ``thermod`` record: the calibration last in force and the recorder's
    attributes."""

    def __init__(self, path: str | os.PathLike, calibration: Calibration | None = None,
                 flush_s: float = 1.0):
        self.path = Path(path)
        self._w = McapWriter(self.path, compress=False)
        self.n_frames = 0
        self.shape: tuple | None = None
        self.n_gyro = 0
        self.health = 0
        self.calibration: dict | None = None        # the last health message's, as received
        self.dropped = 0
        self.source: str | None = None               # where the calibration in force came from
        self._in_force: Calibration | None = None
        self._in_force_json: str | None = None
        self._pending: list[tuple[float, int]] = []  # raw frames still without their CameraInfo
        self._unusable_health = False
        self._flush_s, self._last_flush = flush_s, time.monotonic()
        if calibration is not None:
            self._put_calibration(calibration, "config", None)

    @property
    def empty(self) -> bool:
        return self.n_frames == 0 and self.n_gyro == 0

    def add(self, topic: str, header: dict, array: np.ndarray) -> None:
        t = header.get("t")
        if topic == "raw":
            if array.ndim != 2 or array.dtype != np.uint16 or t is None or not np.isfinite(t):
                self.dropped += 1
                return
            fid = int(header.get("frame_id", self.n_frames))
            self._w.raw(array, float(t), fid)
            self.shape = self.shape or array.shape
            self.n_frames += 1
            if self._in_force is None:
                self._pending.append((float(t), fid))
            else:
                self._w.camera_info(self._in_force, float(t), fid)
        elif topic == "frame":
            if array.ndim == 2 and t is not None and np.isfinite(t):
                self._w.deblurred(np.asarray(array, np.float32), float(t), int(header.get("frame_id", 0)))
        elif topic == "gyro":
            self._w.gyro(array["t"], array["rate"], int(header.get("sample_seq", self.n_gyro)))
            self.n_gyro += len(array)
        elif topic == "health":
            self.health += 1
            if isinstance(header.get("calibration"), dict):
                self.calibration = header["calibration"]
                self._health_calibration(self.calibration, t)
        self.tick()

    def tick(self) -> None:
        """End the chunk and flush the file if `flush_s` have passed since the last time: a killed
        recorder then loses at most about that much of what it received. Called after each message
        and by `thermod.cli.record.record` while nothing arrives."""
        if time.monotonic() - self._last_flush >= self._flush_s:
            self._flush()

    def _flush(self) -> None:
        self._w.flush()
        self._last_flush = time.monotonic()

    def _health_calibration(self, d: dict, t) -> None:
        if self.source == "config":          # --config wins over the daemon's
            return
        try:
            calibration = Calibration.from_dict(d)
        except (TypeError, ValueError, KeyError) as e:
            if not self._unusable_health:    # once: health comes every second
                log.warning("%s: the calibration in the health messages is unusable (%s); not written",
                            self.path, e)
                self._unusable_health = True
            return
        ok = t is not None and isinstance(t, (int, float)) and np.isfinite(t)
        self._put_calibration(calibration, "health", float(t) if ok else None)

    def _put_calibration(self, calibration: Calibration, source: str, t: float | None) -> None:
        """Make `calibration` the one in force and write it now, unless it is already in force."""
        if _calibration_json(calibration) == self._in_force_json:
            return
        self._adopt(calibration, source)
        self._flush()           # the frames before it first, so the file's order is the arrival order
        self._w.metadata(calibration, {"calibration_source": source, **({} if t is None else {"from_t": t})})
        self._flush()           # a rare record, and the one an import of a killed recording needs

    def _adopt(self, calibration: Calibration, source: str) -> None:
        self._in_force, self._in_force_json, self.source = calibration, _calibration_json(calibration), source
        for t, fid in self._pending:
            self._w.camera_info(calibration, t, fid)
        self._pending.clear()

    def _defaults(self) -> Calibration:
        h, w = self.shape or (Calibration().height, Calibration().width)
        log.warning("no calibration received (no health messages) nor --config: writing defaults for a "
                    "%dx%d camera; fix them before deblurring", w, h)
        return Calibration(width=w, height=h, cx=(w - 1) / 2, cy=(h - 1) / 2)

    def finish(self, calibration: Calibration | None = None, attrs: dict | None = None) -> Path:
        """The remaining CameraInfo and the final ``thermod`` record; close and rename. Calibration:
        `calibration` (also for frames still without CameraInfo) > the one in force > defaults."""
        try:
            if calibration is not None and _calibration_json(calibration) != self._in_force_json:
                self._adopt(calibration, "config")
            elif self._in_force is None:
                self._adopt(self._defaults(), "defaults")
            self._w.metadata(
                self._in_force,
                {
                    **(attrs or {}),
                    "calibration_source": self.source,
                    "health_messages": self.health,
                    "frames_dropped": self.dropped,
                },
            )
        except RecordingError:
            self._w.abort(keep=True)
            raise
        except (OSError, ValueError) as e:
            self._w.abort(keep=True)
            raise RecordingError(self.path, "file", f"could not complete the MCAP file ({e}); what was "
                                 f"written is in {self._w.part}") from None
        return self._w.commit()

    @property
    def counts(self) -> dict:
        return dict(self._w.counts)

    def close(self) -> None:
        self._w.abort(keep=True)

    def discard(self) -> None:
        self._w.abort()


def _calibration_json(calibration: Calibration) -> str:
    """What tells two calibrations apart (`Calibration` holds arrays: no plain ``==``)."""
    return json.dumps(calibration.as_dict(), sort_keys=True)


# ----------------------------------------------------------------------------------------- reading
class Bag:
    """Messages of a ``.mcap`` file, a rosbag2 directory or a ROS 1 ``.bag``, decoded.

    `topics` maps topic → message type (``sensor_msgs/msg/Image`` style for all three formats);
    `counts` the number of messages per topic; `metadata` the MCAP metadata records by name (the
    last of each name), `metadata_records` all of them as (name, record), in the file's order.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.topics: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.metadata_records: list[tuple[str, dict[str, str]]] = []
        self.truncated = False
        self._file = self._reader = None
        if not self.path.exists():
            raise RecordingError(self.path, "file", "does not exist")
        if self.path.is_file() and is_mcap_name(self.path):
            self._open_mcap()
        elif self.path.is_dir() or self.path.suffix.lower() == ".bag":
            self._open_rosbags()
        else:
            beside = (f" (a rosbag2 .db3 file is read through its directory: give {self.path.parent})"
                      if self.path.suffix.lower() == ".db3" else "")
            raise RecordingError(
                self.path,
                "file",
                "expected an .mcap file (or the .mcap.part of an unfinished one), a rosbag2 directory "
                f"(metadata.yaml + .db3/.mcap) or a ROS 1 .bag{beside}",
            )

    def _open_mcap(self) -> None:
        from mcap.exceptions import McapError
        from mcap.reader import SeekingReader

        self._file = open(self.path, "rb")  # noqa: SIM115 (closed by close())
        try:
            size = os.fstat(self._file.fileno()).st_size
            self._bounded = _Bounded(self._file, size)
            if self._bounded.read(len(MAGIC)) != MAGIC:
                raise RecordingError(self.path, "file", "not a readable MCAP file (it does not start with "
                                     "the MCAP magic)")
            self._check_chunks(size)
            summary = None
            # A file cut short does not end with the magic; its last bytes are not a footer and any
            # offset read there is garbage, so the summary is only looked for before a closing magic.
            if size >= 2 * len(MAGIC):
                self._bounded.seek(size - len(MAGIC))
            if (size >= 2 * len(MAGIC) and self._bounded.read(len(MAGIC)) == MAGIC
                    and self._summary_intact(size)):
                self._bounded.seek(0)     # the reader checks the magic where the file stands
                self._reader = SeekingReader(self._bounded, decoder_factories=[_decoders()],
                                             record_size_limit=size)
                try:
                    summary = self._reader.get_summary()
                except (McapError, *_DAMAGE):
                    summary = None
            if summary is None:
                self._scan(size)
                return
            for cid, ch in summary.channels.items():
                schema = summary.schemas.get(ch.schema_id)
                self.topics[ch.topic] = _ros2_name(schema.name) if schema else "?"
                n = summary.statistics.channel_message_counts.get(cid, 0) if summary.statistics else 0
                self.counts[ch.topic] = self.counts.get(ch.topic, 0) + n
            self.metadata_records = [(m.name, dict(m.metadata)) for m in self._reader.iter_metadata()]
            self.metadata = dict(self.metadata_records)
        except (McapError, OSError, *_DAMAGE) as e:
            self.close()
            raise RecordingError(
                self.path, "file", f"not a readable MCAP file ({type(e).__name__}: {e})"
            ) from None
        except RecordingError:
            self.close()
            raise

    def _check_chunks(self, size: int) -> None:
        """Every chunk the file holds opens within `MAX_CHUNK_BYTES` and matches its CRC
        (`chunk_problem`), and the data section matches the CRC its DataEnd record stores, else a
        `RecordingError` naming the damage. A file cut short is checked up to the cut (`_scan` reads
        it)."""
        from mcap.exceptions import McapError
        from mcap.records import Chunk
        from mcap.stream_reader import CRCValidationError, StreamReader

        self._bounded.seek(0)
        try:
            for record in StreamReader(self._bounded, record_size_limit=size, emit_chunks=True,
                                       validate_crcs=True).records:
                if isinstance(record, Chunk):
                    why = chunk_problem(record)
                    if why is not None:
                        raise RecordingError(self.path, "file", f"not a readable MCAP file: the chunk "
                                             f"ending at byte {self._bounded.pos} {why}")
        except CRCValidationError as e:
            raise RecordingError(self.path, "file", f"not a readable MCAP file: its data section (to byte "
                                 f"{self._bounded.pos}) has CRC-32 {e.actual:#010x}, not the "
                                 f"{e.expected:#010x} its DataEnd record stores: damaged") from None
        except (McapError, *_DAMAGE):
            pass                  # damage or a cut: found again, and reported, where it is read
        self._bounded.seek(0)

    def _summary_intact(self, size: int) -> bool:
        """The summary section matches the CRC the footer stores (none stored: taken as intact). A
        damaged one is not used: `_scan` reads the data section, which `_check_chunks` checked."""
        footer = 1 + 8 + 8 + 8 + 4            # opcode, length, summary_start, summary_offset_start, crc
        at = size - len(MAGIC) - footer
        if at < len(MAGIC):
            return False
        self._bounded.seek(at)
        raw = self._bounded.read(footer)
        start, _, crc = struct.unpack_from("<QQI", raw, 9)
        if raw[0] != 0x02 or crc == 0 or start == 0:
            return raw[0] == 0x02             # not a footer: the reader says why; no summary or no CRC
        if not len(MAGIC) <= start <= at:
            return False
        self._bounded.seek(start)
        value, left = 0, at + footer - 4 - start
        while left > 0:
            block = self._bounded.read(min(left, 1 << 20))
            if not block:
                return False
            value, left = zlib.crc32(block, value), left - len(block)
        if value != crc:
            log.warning("%s: the MCAP summary section is damaged (CRC mismatch): reading the data "
                        "section from the start instead", self.path)
        return value == crc

    def _scan(self, size: int) -> None:
        """Topics, counts and metadata of an MCAP file without a usable summary, read from the start
        (`mcap.stream_reader.StreamReader`) up to its footer or, cut short, its last complete
        message; warns how many messages that leaves. No complete message: a `RecordingError`."""
        from mcap.exceptions import McapError
        from mcap.records import Channel, DataEnd, Footer, Header, Message, Metadata, Schema
        from mcap.stream_reader import StreamReader

        self._reader = None
        self._bounded.seek(0)
        schemas, channels = {}, {}
        n = end = 0
        stop = None
        try:
            for i, record in enumerate(StreamReader(self._bounded, record_size_limit=size).records):
                if i == 0 and not isinstance(record, Header):
                    raise RecordingError(self.path, "file", "not a readable MCAP file (no Header record "
                                         f"after the magic, found {type(record).__name__})")
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                    schema = schemas.get(record.schema_id)
                    self.topics[record.topic] = _ros2_name(schema.name) if schema else "?"
                    self.counts.setdefault(record.topic, 0)
                elif isinstance(record, Message):
                    if record.channel_id not in channels:
                        stop = f"a message on channel {record.channel_id}, which no Channel record declares"
                        break
                    self.counts[channels[record.channel_id].topic] += 1
                    n, end = n + 1, self._bounded.pos
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = dict(record.metadata)
                    self.metadata_records.append((record.name, dict(record.metadata)))
                elif isinstance(record, (DataEnd, Footer)):
                    return                # the data section is complete; the summary only repeats it
        # what a record cut short raises inside the library: its reads come back short (EndOfFile,
        # struct.error), a length runs past the end (RecordLengthLimitExceeded), a string is cut
        except (McapError, *_DAMAGE) as e:
            stop = f"{type(e).__module__}.{type(e).__name__}" + (f": {e}" if str(e) else "")
        except BaseException:
            self.close()
            raise
        if n == 0:
            self.close()
            raise RecordingError(self.path, "file", "not a readable MCAP file: it ends before any complete "
                                 f"message ({size} bytes, no summary; {stop})")
        self.truncated = True
        log.warning("%s: truncated MCAP file (no summary; nothing complete after byte %d of %d: %s): "
                    "recovered the %d complete messages before it", self.path, end, size, stop, n)

    def _open_rosbags(self) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        try:
            self._reader = AnyReader([self.path], default_typestore=get_typestore(Stores.LATEST))
            self._reader.open()
        except (AnyReaderError, OSError, ValueError, KeyError) as e:
            why = " ".join(str(e).split())         # YAML errors span several lines
            meta = self.path / "metadata.yaml"     # its problems name it, or the version it holds
            if self.path.is_dir() and (not meta.exists() or "metadata" in why or "version" in why):
                self._reader = None
                self._open_without_metadata(why)
                return
            if self.path.is_file() and "index" in why.lower():
                raise RecordingError(self.path, "file", "ROS 1 bag without a usable index: a recording "
                                     "killed before it closed leaves one (the index is written last); "
                                     f"`rosbag reindex {self.path.name}` rebuilds it (rosbags: {why})"
                                     ) from None
            raise RecordingError(self.path, "file", f"not a readable rosbag ({why})") from None
        for c in self._reader.connections:
            self.topics[c.topic] = _ros2_name(c.msgtype)
            self.counts[c.topic] = self.counts.get(c.topic, 0) + int(c.msgcount)

    def _open_without_metadata(self, why: str) -> None:
        """A rosbag2 directory whose metadata.yaml rosbags cannot use (`why`): missing (`ros2 bag
        record` writes it last, so a killed recorder leaves none) or damaged. Its one ``.mcap`` file
        is then read on its own, with a warning; anything else is refused, naming what is there."""
        meta = self.path / "metadata.yaml"
        mcaps = sorted(p for p in self.path.iterdir() if p.is_file() and is_mcap_name(p))
        dbs = sorted(p.name for p in self.path.iterdir() if p.suffix == ".db3")
        if len(mcaps) == 1 and not dbs:
            log.warning("%s: not readable as a rosbag2 directory (%s): reading %s on its own",
                        self.path, why, mcaps[0].name)
            self.path = mcaps[0]
            self._open_mcap()
            return
        files = [p.name for p in mcaps] + dbs
        if not files:
            raise RecordingError(self.path, "file", f"not a readable rosbag: no .db3 or .mcap file in it "
                                 f"({why})")
        killed = ("metadata.yaml is missing (a `ros2 bag record` killed before it closed leaves none)"
                  if not meta.exists() else f"not a readable rosbag ({why})")
        raise RecordingError(self.path, "file", f"{killed}: `ros2 bag reindex {self.path}` rebuilds "
                             f"metadata.yaml from {', '.join(files)}")

    def messages(self, topics: Iterable[str]) -> Iterator[tuple[str, object, int]]:
        """(topic, decoded message, log time ns) of `topics`, in log-time order, one at a time."""
        topics = list(topics)
        if self._file is not None:
            from mcap.exceptions import McapError

            try:
                yield from (self._scanned_messages(topics) if self._reader is None else (
                    (channel.topic, msg, message.log_time) for _, channel, message, msg in
                    self._reader.iter_decoded_messages(topics=topics, log_time_order=True)))
            except (McapError, *_DAMAGE) as e:
                raise RecordingError(
                    self.path, ",".join(topics), f"cannot decode a message ({type(e).__name__}: {e})"
                ) from None
            return
        conns = [c for c in self._reader.connections if c.topic in topics]
        for conn, log_ns, data in self._reader.messages(connections=conns):
            try:
                msg = self._reader.deserialize(data, conn.msgtype)
            except Exception as e:  # noqa: BLE001 - rosbags raises several kinds on damaged data
                raise RecordingError(
                    self.path, conn.topic, f"cannot decode a {conn.msgtype} message ({type(e).__name__}: {e})"
                ) from None
            yield conn.topic, msg, int(log_ns)

    def _scanned_messages(self, topics: list[str]) -> Iterator[tuple[str, object]]:
        """A file without a summary, in file order (`mcap.reader.NonSeekingReader`, which would load
        it whole to sort by log time): the messages `_scan` counted, no further, so the cut end is
        never read."""
        from mcap.reader import NonSeekingReader

        left = sum(self.counts.get(t, 0) for t in set(topics))
        if left == 0:
            return
        self._bounded.seek(0)
        reader = NonSeekingReader(self._bounded, decoder_factories=[_decoders()],
                                  record_size_limit=self._bounded.size)
        for _, channel, message, msg in reader.iter_decoded_messages(topics=topics, log_time_order=False):
            yield channel.topic, msg, message.log_time
            left -= 1
            if left == 0:
                return

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        elif self._reader is not None:
            self._reader.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


MAGIC = b"\x89MCAP0\r\n"
# a chunk's uncompressed size at most (recorders write chunks of 1–4 MiB; one 4096² float32 frame is
# 64 MiB): a damaged or crafted size field, or a compression bomb, is refused before it is allocated
MAX_CHUNK_BYTES = 256 * 2**20
# What the mcap readers raise, besides McapError, on a damaged record: a short read (EndOfFile,
# struct.error), a string cut or not UTF-8, a garbage u64 length (OverflowError from an in-memory read),
# compressed data that does not decompress (lz4's and zstd's RuntimeError) in a chunk stored with no CRC
_DAMAGE = (ValueError, KeyError, EOFError, IndexError, struct.error, OverflowError, RuntimeError)


def _decoders():
    """mcap-ros2-support's CDR decoders, with every failure — a schema that does not parse (its parser
    raises its own kinds and prints to stderr), a message its schema does not decode — reported as
    the `McapError` `Bag.messages` turns into a RecordingError naming the file and topic."""
    import contextlib
    import io

    from mcap.exceptions import McapError
    from mcap_ros2.decoder import DecoderFactory

    class Decoders(DecoderFactory):
        def decoder_for(self, message_encoding, schema):
            name = getattr(schema, "name", "?")
            try:
                with contextlib.redirect_stderr(io.StringIO()):
                    decode = super().decoder_for(message_encoding, schema)
            except Exception as e:  # noqa: BLE001 - the vendored rosidl parser raises its own kinds
                raise McapError(f"schema {name!r} is not a valid ros2msg definition "
                                f"({type(e).__name__}: {e})") from None
            if decode is None:
                return None

            def guarded(data: bytes):
                try:
                    return decode(data)
                except Exception as e:  # noqa: BLE001 - CDR decoding of damaged bytes raises any kind
                    raise McapError(f"a message does not decode as its schema {name!r} "
                                    f"({type(e).__name__}: {e})") from None
            return guarded

    return Decoders()


def is_mcap_name(path: str | os.PathLike) -> bool:
    """``X.mcap``, or ``X.mcap.part`` (what a recorder left when it could not finish)."""
    name = Path(path).name.lower()
    return name.endswith((".mcap", ".mcap.part"))


def chunk_problem(chunk, limit: int | None = None) -> str | None:
    """Why an MCAP `Chunk` record cannot be opened within `limit` bytes, or None. Its declared size,
    the size its compressed frame declares and what it decompresses to (decoded up to `limit` + 1
    bytes, never further) are each checked: the mcap library allocates by the first two and, for
    LZ4, grows its output without a bound. Then its records against their CRC (when the writer
    stored one: 0 is none), which the library does not check by default: a flipped byte inside a
    chunk would otherwise be imported as a pixel, a time or a length. `limit`: `MAX_CHUNK_BYTES`
    unless given."""
    limit = MAX_CHUNK_BYTES if limit is None else int(limit)
    declared = int(chunk.uncompressed_size)
    if declared > limit:
        return f"declares {declared} bytes uncompressed, over the {limit} a chunk may hold"
    data = chunk.data
    framed = 0
    try:
        if chunk.compression == "lz4":
            import lz4.frame

            framed = int(lz4.frame.get_frame_info(data).get("content_size") or 0)
            records = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=limit + 1)
        elif chunk.compression == "zstd":
            import io

            import zstandard

            framed = max(0, int(zstandard.frame_content_size(data)))
            with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data)) as r:
                records = r.read(limit + 1)
        elif chunk.compression == "":
            records = data
        else:
            return None        # unknown: the library says
    except Exception as e:     # noqa: BLE001 - lz4 and zstandard raise their own kinds on damage
        return f"its {chunk.compression} data do not decompress ({type(e).__name__}: {e})"
    if framed > limit or len(records) > limit:
        return f"decompresses to more than {limit} bytes ({chunk.compression} ratio bomb or damage)"
    if len(records) != declared:
        return f"decompresses to {len(records)} bytes, not the {declared} it declares"
    crc = zlib.crc32(records)
    if chunk.uncompressed_crc and crc != chunk.uncompressed_crc:
        return (f"holds records whose CRC-32 is {crc:#010x}, not the {chunk.uncompressed_crc:#010x} it "
                "stores: damaged")
    return None


class _Bounded:
    """A binary file whose reads stop at its size. The mcap readers read lengths from the file and
    then ``read(length)``, which allocates `length` bytes up front: on a damaged or cut file a
    garbage length would allocate far more than the file holds."""

    def __init__(self, f, size: int):
        self._f, self.size, self.pos = f, size, f.tell()

    def read(self, n: int = -1) -> bytes:
        left = max(0, self.size - self.pos)
        data = self._f.read(left if n is None or n < 0 else min(n, left))
        self.pos += len(data)
        return data

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        self.pos = self._f.seek(offset, whence)
        return self.pos

    def tell(self) -> int:
        return self.pos


def _ros2_name(msgtype: str) -> str:
    """``sensor_msgs/Image`` (ROS 1 style) → ``sensor_msgs/msg/Image``."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


# Image encodings that are raw detector counts, and their element type; `image_array` also reads
# 32FC1, what thermod writes its deblurred frames as.
RAW_ENCODINGS = {
    "mono16": np.uint16,
    "16UC1": np.uint16,
    "mono8": np.uint8,
    "8UC1": np.uint8,
}
_ENCODINGS = {**RAW_ENCODINGS, "32FC1": np.float32}


def image_array(msg, path, topic: str) -> np.ndarray:
    """A sensor_msgs/Image → [H, W] array in native byte order (uint16, uint8 or float32).
    Rows padded beyond ``width`` (``step`` larger) are cut; anything else malformed is an error
    naming the file and topic."""
    enc = str(msg.encoding)
    if enc not in _ENCODINGS:
        raise RecordingError(
            path, topic, f"image encoding {enc!r} is not one thermod reads ({', '.join(_ENCODINGS)} expected)"
        )
    dt = np.dtype(_ENCODINGS[enc]).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(msg.data, np.uint8)
    size = f"image {w}×{h} {enc}"
    if h <= 0 or w <= 0:
        raise RecordingError(path, topic, f"{size}: height and width must be positive")
    if step < w * dt.itemsize:
        raise RecordingError(path, topic, f"{size}: step {step} is less than a row's {w * dt.itemsize} "
                             f"bytes (width × {dt.itemsize})")
    if data.size < h * step:
        raise RecordingError(path, topic, f"{size}: data holds {data.size} bytes, height × step = "
                             f"{h} × {step} = {h * step} expected")
    rows = np.asarray(data[: h * step], np.uint8).reshape(h, step)[:, : w * dt.itemsize]
    return np.ascontiguousarray(rows).view(dt).reshape(h, w).astype(dt.newbyteorder("="))


def camera_info_intrinsics(msg) -> dict:
    """width, height, fx, fy, cx, cy of a sensor_msgs/CameraInfo (ROS 2 ``k`` or ROS 1 ``K``) and
    whether it declares a non-zero distortion (and its ``distortion_model``)."""
    k = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, np.float64).ravel()
    d = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, np.float64).ravel()
    return {
        "width": int(msg.width),
        "height": int(msg.height),
        "fx": float(k[0]),
        "fy": float(k[4]),
        "cx": float(k[2]),
        "cy": float(k[5]),
        "distorted": bool(np.any(d != 0)),
        "distortion_model": str(getattr(msg, "distortion_model", "")),
    }
