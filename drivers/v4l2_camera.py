"""USB/CSI thermal cameras through V4L2 (OpenCV ``cv2.CAP_V4L2``), as a
:class:`~thermod.drivers.camera_base.CameraSource`.

Every hardware call goes through one seam, ``capture_factory(device_path) -> cv2.VideoCapture``-like
object (``set``, ``get``, ``grab``, ``retrieve``, ``isOpened``, ``release``); tests plug in
:class:`thermod.sim.emu_camera.EmuV4L2Capture`.

Setup order matters for 16-bit raw: FOURCC ``"Y16 "`` first, then ``CONVERT_RGB = 0`` (else OpenCV
converts to 8-bit BGR), then width/height/fps, each read back. Some OpenCV builds hand Y16 frames over
as flat uint8 bytes ([1, 2N], [H, 2W], ...): :func:`~thermod.drivers.camera_base.as_uint16_image`
reshapes them. ``CAP_PROP_POS_MSEC`` is the V4L2 buffer timestamp (kernel clock, ms): mapped to host
CLOCK_MONOTONIC by `ClockMapper`. V4L2 sequence numbers are not exposed by OpenCV,
so lost frames are counted from timestamp gaps. Most V4L2 drivers stamp buffers on CLOCK_MONOTONIC
(``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``): then the timestamp already is host time and is used as is
(``timestamp_clock="auto"`` detects this on the first frame); otherwise (UVC hardware clock, another
clock) it is mapped by `ClockMapper`. Cameras with telemetry lines (FLIR Boson 640×514 =
640×512 image + 2 telemetry rows) have them stripped: ``telemetry_rows=(top, bottom)``.

Flat-field corrections: with telemetry rows and ``telemetry="boson"`` (the default), each frame's FFC
state is read from the Boson telemetry status word (:func:`boson_ffc_state`) and a frame delivered while
it says "FFC in progress" is flagged ``Frame.ffc``.
"""

from __future__ import annotations

import math
import os
import re
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from thermod.drivers.camera_base import (
    Backoff,
    CameraSource,
    Frame,
    as_uint16_image,
    clock_stats,
    count_ffc,
    measured_rate_hz,
)
from thermod.errors import DeviceError
from thermod.io.clock import ClockMapper

FOURCC_Y16 = "Y16 "

# FLIR Boson telemetry line (the first telemetry row, 16-bit words as delivered in Y16): the status
# word is word 38 (byte offset 76); its bits 0–1 hold the FFC state, the FLR_BOSON_FFCSTATUS_E values
# of the Boson SDK (0 never performed, 1 imminent, 2 in progress, 3 complete). Source: FLIR Boson
# Software IDD, telemetry table ("Status bits", word 38), as decoded by the open ROS Boson telemetry
# splitter; byte 76 is also the STATUS field of Elphel's Boson640Telemetry parser. A non-Boson camera
# with telemetry rows needs telemetry=None.
BOSON_STATUS_WORD = 38
BOSON_FFC_STATE_MASK = 0b11
BOSON_FFC_IN_PROGRESS = 2


def boson_ffc_state(telemetry: np.ndarray) -> int | None:
    """The FFC state (0–3, see `BOSON_STATUS_WORD`) from Boson telemetry rows (uint16 [rows, W]), or
    None when there is no telemetry line long enough to hold the status word."""
    if telemetry.ndim != 2 or telemetry.shape[0] < 1 or telemetry.shape[1] <= BOSON_STATUS_WORD:
        return None
    return int(telemetry[0, BOSON_STATUS_WORD]) & BOSON_FFC_STATE_MASK


def fourcc_code(s: str) -> int:
    """The V4L2/OpenCV integer code of a four-character code ("Y16 " → 0x20363159)."""
    if len(s) != 4:
        raise DeviceError(f"FOURCC must be 4 characters, got {s!r}")
    return sum(ord(c) << (8 * i) for i, c in enumerate(s))


def fourcc_str(code: float) -> str:
    c = int(code)
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4))


def resolve_device(device: str | int | os.PathLike) -> str:
    """Resolve a camera given as index, ``videoN``, ``/dev/videoN`` or a stable ``/dev/v4l/by-id/...``
    (or ``by-path``) symlink to its ``/dev/videoN`` path. Raises DeviceError if it does not exist."""
    path = os.fspath(device) if not isinstance(device, int) else str(device)
    if path.isdigit():
        path = f"/dev/video{path}"
    elif re.fullmatch(r"video\d+", path):
        path = "/dev/" + path
    if not os.path.exists(path):
        hint = ""
        if "/by-id/" in path or "/by-path/" in path:
            d = os.path.dirname(path)
            listing = sorted(os.listdir(d)) if os.path.isdir(d) else []
            hint = f"; {d} has {listing or 'nothing'}"
        raise DeviceError(f"V4L2 camera {path}: no such device (is it plugged in? `v4l2-ctl "
                          f"--list-devices`{hint})")
    return os.path.realpath(path)


def opencv_capture(path: str):
    """The real seam: OpenCV's V4L2 backend. Opened by index (``/dev/videoN`` → N), which every OpenCV
    build supports; some builds cannot open a V4L2 device by file name."""
    import cv2

    m = re.fullmatch(r"/dev/video(\d+)", path)
    return cv2.VideoCapture(int(m.group(1)) if m else path, cv2.CAP_V4L2)


class V4L2Camera(CameraSource):
    """V4L2 camera source.

    Parameters
    ----------
    device
        ``/dev/v4l/by-id/...`` (stable across replugging, preferred), ``/dev/videoN`` or an index.
    width, height
        Image size after the telemetry rows are stripped; the device is asked for
        ``height + top + bottom`` rows.
    frame_rate_hz
        Requested rate (None keeps the device's); also the nominal rate for gap counting.
    telemetry_rows
        ``(top, bottom)`` rows of the device frame that are not image (Boson: 2 rows, top or bottom
        depending on its configuration).
    telemetry
        Layout of the telemetry rows: ``"boson"`` (FLIR Boson: FFC state from the status word, see
        :func:`boson_ffc_state`) or None (rows stripped, not interpreted: frames never flagged FFC).
    capture_factory
        ``path -> VideoCapture``-like; default :func:`opencv_capture`.
    timestamp_clock
        ``"monotonic"``: buffer timestamps are host CLOCK_MONOTONIC; ``"device"``: an unrelated clock,
        mapped by a ClockMapper; ``"auto"``: monotonic if the first timestamp is within 1 s of its arrival.
    timestamp_offset_s
        Added to the mapped buffer timestamp so that ``Frame.t`` is when the last row was read (UVC
        drivers stamp the start of the frame: use +1/fps there).
    read_timeout_s
        How long a single ``grab`` may block (``CAP_PROP_READ_TIMEOUT_MSEC`` where supported).
    reopen
        After a failed read, release the device and reopen it with backoff (``backoff_s``) in later
        polls (USB cameras get replugged); False raises DeviceError instead.
    """

    def __init__(self, device: str | int | os.PathLike, *, width: int = 640, height: int = 512,
                 frame_rate_hz: float | None = None, telemetry_rows: tuple[int, int] = (0, 0),
                 telemetry: str | None = "boson", fourcc: str = FOURCC_Y16,
                 capture_factory: Callable | None = None,
                 timestamp_clock: str = "auto", timestamp_offset_s: float = 0.0, read_timeout_s: float = 1.0,
                 reopen: bool = True, backoff_s: tuple[float, float] = (0.2, 5.0), name: str | None = None):
        top, bottom = (int(v) for v in telemetry_rows)
        if min(top, bottom) < 0 or width <= 0 or height <= 0:
            raise DeviceError(f"V4L2 camera {device}: width/height must be > 0 and telemetry_rows ≥ 0, got "
                              f"{width}×{height}, telemetry_rows={telemetry_rows!r}")
        if frame_rate_hz is not None and not (frame_rate_hz > 0 and math.isfinite(frame_rate_hz)):
            raise DeviceError(f"V4L2 camera {device}: frame_rate_hz must be > 0, got {frame_rate_hz!r}")
        self.device = os.fspath(device) if not isinstance(device, int) else device
        self.name = name or f"v4l2:{device}"
        self.width, self.height = int(width), int(height)
        self.top, self.bottom = top, bottom
        self.raw_height = self.height + top + bottom
        if telemetry not in ("boson", None):
            raise DeviceError(f"V4L2 camera {device}: telemetry must be 'boson' or None, got {telemetry!r}")
        self.telemetry = telemetry if top + bottom else None
        self._in_ffc = False
        self.req_rate = frame_rate_hz
        self.fourcc = fourcc
        self.factory = capture_factory or opencv_capture
        if timestamp_clock not in ("auto", "monotonic", "device"):
            raise DeviceError(f"{self.name}: timestamp_clock must be 'auto', 'monotonic' or 'device', got "
                              f"{timestamp_clock!r}")
        self.timestamp_clock = timestamp_clock
        self._monotonic: bool | None = {"auto": None, "monotonic": True, "device": False}[timestamp_clock]
        self.timestamp_offset_s = float(timestamp_offset_s)
        self.read_timeout_s = float(read_timeout_s)
        self.reopen = bool(reopen)
        self._backoff = Backoff(*backoff_s)
        self.path: str | None = None
        self._cap = None
        self._running = False
        self.state = "stopped"
        self.frame_rate_hz = math.nan
        self.clock: ClockMapper | None = None
        self._frame_id = -1
        self._last_ts: int | None = None
        self._last_t = math.nan
        self._recent = deque(maxlen=64)
        self.counters = {"frames": 0, "frames_lost": 0, "gap_events": 0, "read_errors": 0, "bad_frames": 0,
                         "reopens": 0, "reopen_attempts": 0, "timestamp_fallbacks": 0, "flat_frames": 0,
                         "ffc_frames": 0, "ffc_events": 0}
        self.last_error = ""

    # -- session -------------------------------------------------------------------------------
    def start(self) -> None:
        if self._running:
            return
        self._open()
        self._running = True

    def stop(self) -> None:
        self._running = False
        self._release()
        self.state = "stopped"

    def _release(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            try:
                cap.release()
            except Exception:
                pass

    def _open(self) -> None:
        import cv2

        if self.factory is opencv_capture or os.path.lexists(str(self.device)):
            self.path = resolve_device(self.device)     # by-id symlink → /dev/videoN
        else:
            self.path = str(self.device)                # an injected capture seam names its own devices
        cap = self.factory(self.path)
        if cap is None or not cap.isOpened():
            raise DeviceError(f"{self.name}: cannot open {self.path} (permissions? the video group, udev "
                              "rules; is another program streaming from it?)")
        try:
            self._configure(cv2, cap)
        except DeviceError:
            cap.release()
            raise
        self._cap = cap
        self.clock = ClockMapper(1e-6, name=f"{self.name} buffer timestamp")
        self._last_ts = None
        self.state = "streaming"

    def _configure(self, cv2, cap) -> None:
        code = fourcc_code(self.fourcc)
        cap.set(cv2.CAP_PROP_FOURCC, code)
        got = fourcc_str(cap.get(cv2.CAP_PROP_FOURCC))
        if got != self.fourcc:
            raise DeviceError(f"{self.name}: pixel format {self.fourcc!r} not accepted (device uses "
                              f"{got!r}); check `v4l2-ctl --list-formats-ext` for a 16-bit raw mode")
        # Only after the FOURCC: OpenCV resets conversion when the format changes.
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.raw_height)
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (w, h) != (self.width, self.raw_height):
            raise DeviceError(f"{self.name}: frame size {self.width}×{self.raw_height} (image "
                              f"{self.width}×{self.height} + telemetry {self.top}+{self.bottom} rows) not "
                              f"accepted, device delivers {w}×{h}; check width/height/telemetry_rows")
        if self.req_rate is not None:
            cap.set(cv2.CAP_PROP_FPS, float(self.req_rate))
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            if not abs(fps - self.req_rate) <= 0.01 * self.req_rate:
                raise DeviceError(f"{self.name}: frame rate {self.req_rate} Hz not accepted (device runs "
                                  f"{fps:g} Hz)")
        self.frame_rate_hz = float(cap.get(cv2.CAP_PROP_FPS))
        if hasattr(cv2, "CAP_PROP_READ_TIMEOUT_MSEC"):
            cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(self.read_timeout_s * 1000))

    def _on_read_error(self, why: str) -> None:
        self.counters["read_errors"] += 1
        self.last_error = why
        self._release()
        if not self.reopen:
            self.state = "lost"
            raise DeviceError(f"{self.name}: {why}; check the cable/USB port (dmesg)")
        self.state = "reopening"
        self._backoff.restart(at_once=False)

    def _try_reopen(self, deadline: float) -> bool:
        if not self._backoff.due(deadline):
            return False
        self.counters["reopen_attempts"] += 1
        try:
            self._open()
        except DeviceError as e:
            self.last_error = str(e)
            self._backoff.failed()
            return False
        self.counters["reopens"] += 1
        return True

    # -- frames --------------------------------------------------------------------------------
    def poll(self, timeout: float) -> Frame | None:
        """Next frame, or None. V4L2 reads cannot be interrupted: a ``grab`` may outlast ``timeout`` by up
        to one frame period (bounded by ``read_timeout_s``)."""
        import cv2

        if not self._running:
            raise DeviceError(f"{self.name}: poll() before start()")
        deadline = time.monotonic() + max(0.0, timeout)
        while True:
            if self.state == "lost":
                raise DeviceError(f"{self.name}: {self.last_error}")
            if self.state != "streaming" and not self._try_reopen(deadline):
                if time.monotonic() >= deadline:
                    return None
                continue
            cap = self._cap
            if not cap.grab():
                self._on_read_error("read failed (device unplugged or timed out)")
                continue
            arrival = time.monotonic()
            ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
            ok, data = cap.retrieve()
            if not ok or data is None:
                self._on_read_error("retrieve failed")
                continue
            try:
                raw = as_uint16_image(data, self.raw_height, self.width, self.name)
            except DeviceError as e:
                self.counters["bad_frames"] += 1
                self.last_error = str(e)
                raise
            if data.dtype == np.uint8 or data.ndim != 2 or data.shape[0] != self.raw_height:
                self.counters["flat_frames"] += 1
            image = raw[self.top:self.raw_height - self.bottom]
            frame = self._frame(image, ms, arrival)
            frame.ffc = self._ffc(raw)
            return frame

    def _ffc(self, raw: np.ndarray) -> bool:
        """Whether the frame's telemetry says a flat-field correction is in progress (counted)."""
        if self.telemetry is None:
            return False
        rows = raw[:self.top] if self.top else raw[self.raw_height - self.bottom:]
        ffc = boson_ffc_state(rows) == BOSON_FFC_IN_PROGRESS
        count_ffc(self.counters, self._in_ffc, ffc)
        self._in_ffc = ffc
        return ffc

    def _frame(self, image: np.ndarray, ms: float, arrival: float) -> Frame:
        ts = int(round(ms * 1000.0))                   # µs ticks: exact ints for the clock fit
        if ts <= 0:
            # driver without buffer timestamps: the read time is all there is
            self.counters["timestamp_fallbacks"] += 1
            ts = int(round(arrival * 1e6))
        gap = 0
        if self._last_ts is not None and self.frame_rate_hz > 0 and ts > self._last_ts:
            gap = max(0, round((ts - self._last_ts) * 1e-6 * self.frame_rate_hz) - 1)
        elif self._frame_id >= 0 and math.isfinite(self._last_t) and self.frame_rate_hz > 0:
            gap = max(0, round((arrival - self._last_t) * self.frame_rate_hz) - 1)   # after a reopen
        if gap:
            self.counters["gap_events"] += 1
            self.counters["frames_lost"] += gap
        if self._monotonic is None:
            self._monotonic = abs(ts * 1e-6 - arrival) < 1.0
        if self._monotonic:
            t = ts * 1e-6 + self.timestamp_offset_s
        else:
            self.clock.observe(ts, arrival)
            t = float(self.clock.to_host(ts)) + self.timestamp_offset_s
        self._frame_id += 1 + gap
        self._last_ts = ts
        self._last_t = t
        self.counters["frames"] += 1
        self._recent.append(arrival)
        image = np.ascontiguousarray(image)
        return Frame(image=image, t=t, frame_id=self._frame_id, device_ts=ts, arrival=arrival, gap_before=gap)

    def stats(self) -> dict:
        rate = measured_rate_hz(self._recent)
        out = {"state": self.state, "device": self.path or str(self.device), "width": self.width,
               "height": self.height, "telemetry_rows": (self.top, self.bottom),
               "frame_rate_hz": self.frame_rate_hz, "measured_rate_hz": rate, "last_error": self.last_error,
               **self.counters}
        if self.clock is not None:
            out["timestamp_clock"] = {None: "unknown", True: "monotonic", False: "device"}[self._monotonic]
        if self.clock is not None and self._monotonic is False:
            out.update(clock_stats(self.clock))
        return out
