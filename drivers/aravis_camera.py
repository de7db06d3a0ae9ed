"""GigE Vision camera through Aravis 0.8 (PyGObject), as a :class:`~thermod.drivers.camera_base.CameraSource`.

Opens by IP address or by device id/serial (after ``Aravis.update_device_list()``), sets Mono16 (or
Mono14 in 16-bit containers), region, frame rate and GVSP packet size explicitly, and streams into a
buffer pool sized for bursts. Device timestamps (``ArvBuffer.get_timestamp()``, ns) are mapped to host
CLOCK_MONOTONIC by `ClockMapper`; 16-bit block ids are unwrapped and gaps counted;
buffers whose status is not SUCCESS are counted and dropped.

Loss of the camera (``control-lost`` from the heartbeat, or a silent stream that no longer answers a
GVCP discovery probe) tears the session down; later ``poll`` calls reopen it with exponential backoff
and count the reconnect. A cheap unicast discovery probe (one UDP packet, ~100 ms timeout) guards every
reopen, so ``poll`` stays bounded by its timeout while the camera is away (a full Aravis open of an
absent camera blocks for seconds).
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from collections import deque

from thermod.drivers.camera_base import (
    Backoff,
    CameraSource,
    Frame,
    FrameIdTracker,
    as_uint16_image,
    clock_stats,
    count_ffc,
    measured_rate_hz,
)
from thermod.errors import DeviceError
from thermod.io.clock import ClockMapper

GVCP_PORT = 3956
# Aravis' heartbeat thread emits control-lost at most once, at the end of a check that retries a dead
# camera's register for up to 5 s (ARV_GV_DEVICE_HEARTBEAT_RETRY_TIMEOUT_S) of GVCP reads of 2.5 s
LAST_CONTROL_LOST_S = 8.0
_GVCP_DISCOVERY_CMD = 0x0002
_GVCP_DISCOVERY_ACK = 0x0003
# Pixel formats whose pixels sit in little-endian 16-bit containers (PFNC codes).
PIXEL_FORMATS_16 = {"Mono16": 0x01100007, "Mono14": 0x01100025, "Mono12": 0x01100005}

_aravis = None


def load_aravis():
    """Import Aravis 0.8 through PyGObject, or raise DeviceError saying what to install."""
    global _aravis
    if _aravis is None:
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis
        except (ImportError, ValueError) as e:
            raise DeviceError("GigE Vision needs Aravis 0.8 through PyGObject: install the Debian packages "
                              "gir1.2-aravis-0.8 aravis-tools and `pip install 'PyGObject<3.51'` "
                              f"({e})") from None
        _aravis = Aravis
    return _aravis


def gvcp_probe(address: str, timeout: float = 0.1, port: int = GVCP_PORT) -> dict | None:
    """Unicast a GVCP DISCOVERY_CMD to ``address``; return {manufacturer, model, serial} or None.

    Needs no control privilege, so it works while another client (or a stale session) holds the camera.
    """
    req_id = int(time.monotonic_ns() & 0xFFFF) or 1
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(max(timeout, 1e-3))
        try:
            s.sendto(struct.pack(">BBHHH", 0x42, 0x01, _GVCP_DISCOVERY_CMD, 0, req_id), (address, port))
            deadline = time.monotonic() + timeout
            while True:
                data, _ = s.recvfrom(2048)
                status, ack, length, rid = struct.unpack(">HHHH", data[:8])
                if ack == _GVCP_DISCOVERY_ACK and rid == req_id and status == 0 and len(data) >= 8 + 0xE8:
                    p = data[8:]

                    def txt(a, b, p=p):
                        return p[a:b].split(b"\0", 1)[0].decode("ascii", "replace")

                    return {"manufacturer": txt(0x48, 0x68), "model": txt(0x68, 0x88),
                            "serial": txt(0xD8, 0xE8)}
                if time.monotonic() >= deadline:
                    return None
        except OSError:        # timeout, unreachable, refused
            return None


class AravisCamera(CameraSource):
    """GigE Vision camera source.

    Parameters
    ----------
    address
        IP address (or host name) of the camera; opened directly, no discovery broadcast needed.
    device_id
        Alternatively an Aravis device id, serial number or user-defined name, resolved after
        ``Aravis.update_device_list()`` (a discovery broadcast: ~1 s). After a loss the last address
        is probed; a new discovery (the camera may come back on another IP) is tried every 10 s.
    width, height, offset_x, offset_y
        Region of interest; None keeps the camera's current width/height.
    frame_rate_hz
        Acquisition frame rate; None keeps the camera's setting. Read back and checked to 1 %.
    pixel_formats
        Formats to try in order; all must be 16-bit containers (Mono14 data arrives as Mono16 words).
    packet_size
        GVSP packet size in bytes (``GevSCPSPacketSize``): 1500 fits a standard MTU, 8000–9000 needs
        jumbo frames. None, or a camera without the feature, negotiates with ``gv_auto_packet_size``.
    n_buffers
        Stream buffer pool; default holds 0.5 s of frames (at least 16) so bursts and a late consumer
        do not drop frames inside Aravis.
    timestamp_offset_s
        Added to the mapped device timestamp so that ``Frame.t`` is when the last row was read (cameras
        latch the timestamp at different points of the frame).
    reconnect
        After a loss, reopen with backoff (``backoff_s`` = (first, max) delay). False: raise DeviceError.
    stall_timeout_s
        Without frames for this long, probe the camera; no answer means it is gone.
    features
        Extra GenICam features to set after opening, e.g. ``{"ExposureTime": 1000.0}``.
    ffc_feature
        GenICam feature that reports a flat-field correction (shutter closed / NUC) in progress, read
        once per frame; its value flags ``Frame.ffc`` (see :func:`ffc_value`). None: the first of
        `FFC_STATUS_FEATURES` the camera offers. A camera offering none of them never flags FFC.
    """

    def __init__(self, address: str | None = None, *, device_id: str | None = None, width: int | None = None,
                 height: int | None = None, offset_x: int = 0, offset_y: int = 0,
                 frame_rate_hz: float | None = None, pixel_formats=("Mono16", "Mono14"),
                 packet_size: int | None = 1500, n_buffers: int | None = None,
                 timestamp_offset_s: float = 0.0,
                 reconnect: bool = True, backoff_s: tuple[float, float] = (0.2, 5.0),
                 stall_timeout_s: float | None = None, features: dict | None = None, name: str | None = None,
                 ffc_feature: str | None = None):
        if (address is None) == (device_id is None):
            raise DeviceError("GigE camera: give exactly one of address= (IP) or device_id= (id/serial/name)")
        bad = [p for p in pixel_formats if p not in PIXEL_FORMATS_16]
        if bad or not pixel_formats:
            raise DeviceError(f"GigE camera: pixel_formats must be among {sorted(PIXEL_FORMATS_16)}, got "
                              f"{list(pixel_formats)!r}")
        if frame_rate_hz is not None and not (frame_rate_hz > 0 and math.isfinite(frame_rate_hz)):
            raise DeviceError(f"GigE camera: frame_rate_hz must be > 0, got {frame_rate_hz!r}")
        self.address, self.device_id = address, device_id
        self.name = name or f"gige:{address or device_id}"
        self.req_width, self.req_height = width, height
        self.offset_x, self.offset_y = int(offset_x), int(offset_y)
        self.req_rate = frame_rate_hz
        self.pixel_formats = tuple(pixel_formats)
        self.req_packet_size = packet_size
        self.req_buffers = n_buffers
        self.timestamp_offset_s = float(timestamp_offset_s)
        self.reconnect = bool(reconnect)
        self._backoff = Backoff(*backoff_s)
        self.req_stall = stall_timeout_s
        self.features = dict(features or {})
        self.req_ffc_feature = ffc_feature
        self.ffc_feature: str | None = None     # the status feature found on the open camera
        self._in_ffc = False

        self._lock = threading.RLock()
        self._cam = self._stream = self._device = None
        self._lost = threading.Event()        # set from Aravis' heartbeat thread on control-lost
        self._running = False
        self.state = "stopped"
        self.tracker = FrameIdTracker()
        self.clock: ClockMapper | None = None
        self._resolved_address: str | None = address
        self.rediscover_s = 10.0
        self._lost_since = self._last_discovery = -math.inf
        self._last_arrival = math.nan
        self._last_t = math.nan
        self._recent = deque(maxlen=64)       # arrival times for the measured rate
        self.width = self.height = 0
        self.frame_rate_hz = math.nan
        self.pixel_format = ""
        self.packet_size = 0
        self.counters = {"bad_buffers": 0, "wrong_size": 0, "disconnects": 0, "reconnects": 0,
                         "reconnect_attempts": 0, "stalls": 0, "timestamp_fallbacks": 0, "outage_frames": 0,
                         "ffc_frames": 0, "ffc_events": 0, "ffc_read_errors": 0}
        self.bad_status: dict[str, int] = {}
        self.last_error = ""

    # -- session -------------------------------------------------------------------------------
    def start(self) -> None:
        """Open the camera, configure it and start acquisition. Raises DeviceError when it cannot."""
        with self._lock:
            if self._running:
                return
            self._open()
            self._running = True

    def stop(self) -> None:
        """Stop acquisition and release the camera. Never blocks on a camera that has gone away (the
        supervisor restarts sources that stall: a register write to a dead camera would hang ~5 s)."""
        with self._lock:
            self._running = False
            addr = self._resolved_address
            alive = self._cam is not None and not self._lost.is_set() and (
                addr is None or gvcp_probe(addr, 0.2) is not None)     # < 1 ms when it answers
            self._teardown(stop_device=alive)
            self.state = "stopped"

    def _open(self) -> None:
        Aravis = load_aravis()
        target = self.address
        if target is None and self._resolved_address is not None:
            # reopening by id: the last address is a cheap first guess if the same camera answers there
            # (a discovery broadcast over every interface takes a second or more)
            info = gvcp_probe(self._resolved_address, timeout=0.3)
            if info and info["serial"] and (self.device_id == info["serial"]
                                            or self.device_id.endswith("-" + info["serial"])):
                target = self._resolved_address
        if target is not None and gvcp_probe(target, timeout=0.3) is None:
            # fail fast: opening an absent camera would block for its GVCP retries (seconds)
            raise DeviceError(f"{self.name}: no GigE Vision camera answers at {target} (GVCP discovery on "
                              f"UDP {GVCP_PORT}); check power, cable, the camera's IP/subnet, firewall")
        try:
            if target is None:
                target, self._resolved_address = self._resolve(Aravis)
            cam = Aravis.Camera.new(target)
        except DeviceError:
            raise
        except Exception as e:   # GLib.GError
            raise DeviceError(f"{self.name}: cannot open GigE camera {target!r} ({_msg(e)}); check power, "
                              "cable and IP (`arv-tool-0.8` lists reachable cameras) and that no other "
                              "program holds control") from None
        try:
            self._configure(Aravis, cam)
        except DeviceError:
            _safe(cam.stop_acquisition)
            raise
        except Exception as e:
            _safe(cam.stop_acquisition)
            raise DeviceError(f"{self.name}: configuring the camera failed ({_msg(e)})") from None
        self.state = "streaming"
        self._last_arrival = time.monotonic()

    def _resolve(self, Aravis) -> tuple[str, str | None]:
        Aravis.update_device_list()
        seen = []
        for i in range(Aravis.get_n_devices()):
            ids = {Aravis.get_device_id(i), Aravis.get_device_serial_nbr(i), Aravis.get_device_physical_id(i),
                   f"{Aravis.get_device_vendor(i)}-{Aravis.get_device_serial_nbr(i)}"}
            seen.append(Aravis.get_device_id(i))
            if self.device_id in ids:
                return Aravis.get_device_id(i), Aravis.get_device_address(i)
        raise DeviceError(f"{self.name}: no GigE camera with id/serial {self.device_id!r} found "
                          f"(discovered: {seen or 'none'}); check the cable, the camera's IP subnet and "
                          "the firewall (UDP 3956)")

    def _configure(self, Aravis, cam) -> None:
        dev = cam.get_device()
        for fmt in self.pixel_formats:
            if dev.is_enumeration_entry_available("PixelFormat", fmt):
                cam.set_pixel_format_from_string(fmt)
                break
        else:
            avail = list(cam.dup_available_pixel_formats_as_strings())
            raise DeviceError(f"{self.name}: camera offers none of the 16-bit formats "
                              f"{list(self.pixel_formats)} (available: {avail}); thermal cameras need "
                              "Mono16/Mono14 raw counts")
        self.pixel_format = cam.get_pixel_format_as_string()
        _, _, cur_w, cur_h = cam.get_region()
        w = int(self.req_width or cur_w)
        h = int(self.req_height or cur_h)
        cam.set_region(self.offset_x, self.offset_y, w, h)
        got = tuple(cam.get_region())
        if got != (self.offset_x, self.offset_y, w, h):
            raise DeviceError(f"{self.name}: region (x, y, w, h) {(self.offset_x, self.offset_y, w, h)} "
                              f"not accepted, camera has {got}; check the sensor size and increments")
        self.width, self.height = w, h
        for k, v in self.features.items():
            _set_feature(dev, k, v, self.name)
        self.ffc_feature = self._find_ffc_feature(dev)
        if self.req_rate is not None:
            cam.set_frame_rate(float(self.req_rate))
            rate = cam.get_frame_rate()
            if abs(rate - self.req_rate) > 0.01 * self.req_rate:
                lo, hi = cam.get_frame_rate_bounds()
                raise DeviceError(f"{self.name}: frame rate {self.req_rate} Hz not accepted (camera runs "
                                  f"{rate:g} Hz, bounds {lo:g}–{hi:g} Hz)")
        self.frame_rate_hz = float(cam.get_frame_rate())
        if self.req_packet_size and dev.is_feature_available("GevSCPSPacketSize"):
            cam.gv_set_packet_size(int(self.req_packet_size))
        else:
            cam.gv_auto_packet_size()
        self.packet_size = int(cam.gv_get_packet_size())
        cam.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
        stream = cam.create_stream(None, None)
        if stream is None:
            raise DeviceError(f"{self.name}: could not create the GVSP stream (check the firewall for "
                              "incoming UDP from the camera)")
        payload = cam.get_payload()
        n = self.req_buffers or max(16, math.ceil(0.5 * self.frame_rate_hz))
        for _ in range(n):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self.n_buffers = n
        lost = threading.Event()          # one per session: a stale session's late signal is ignored
        dev.connect("control-lost", lambda *_: lost.set())
        self._lost = lost
        self._cam, self._device, self._stream = cam, dev, stream
        self.clock = ClockMapper(1e-9, name=f"{self.name} timestamp")
        self.tracker.resync()
        cam.start_acquisition()
        if self._resolved_address is None:
            self._resolved_address = _safe(lambda: dev.get_device_address().to_string())

    def _find_ffc_feature(self, dev) -> str | None:
        if self.req_ffc_feature is not None:
            if not dev.is_feature_available(self.req_ffc_feature):
                raise DeviceError(f"{self.name}: GenICam feature {self.req_ffc_feature!r} (ffc_feature) not "
                                  "available on this camera")
            return self.req_ffc_feature
        return next((f for f in FFC_STATUS_FEATURES if dev.is_feature_available(f)), None)

    def _read_ffc(self) -> bool:
        """The camera's FFC status for the frame just received (one GVCP register read), counted."""
        if self.ffc_feature is None or self._device is None:
            return False
        try:
            ffc = ffc_value(self._device.get_feature(self.ffc_feature).get_value_as_string())
        except Exception as e:   # GLib.GError: a failed read must not lose the frame
            self.counters["ffc_read_errors"] += 1
            self.last_error = f"reading {self.ffc_feature}: {_msg(e)}"
            ffc = self._in_ffc            # keep the last known state
        count_ffc(self.counters, self._in_ffc, ffc)
        self._in_ffc = ffc
        return ffc

    def _teardown(self, stop_device: bool = True) -> None:
        session = [self._cam, self._stream, self._device]
        self._cam = self._stream = self._device = None
        if session[0] is None:
            return
        if stop_device:
            _safe(session[0].stop_acquisition)
            session.clear()       # closes the GVCP control channel and the stream socket
        else:
            # After a loss, releasing the device tries to give up control of a dead camera and blocks
            # for its GVCP retries (~8 s, GIL released): let a reaper thread wait for that, not poll().
            threading.Thread(target=_release_lost, args=(session, self._lost), name=f"{self.name} release",
                             daemon=True).start()

    def _on_lost(self, why: str) -> None:
        self.counters["disconnects"] += 1
        self.last_error = why
        self._teardown(stop_device=False)
        if not self.reconnect:
            self.state = "lost"
            raise DeviceError(f"{self.name}: camera lost ({why}); check power, cable and IP")
        self.state = "reconnecting"
        self._backoff.restart(at_once=True)
        self._lost_since = time.monotonic()

    def _try_reconnect(self, deadline: float) -> bool:
        if not self._backoff.due(deadline):
            return False
        now = time.monotonic()
        self.counters["reconnect_attempts"] += 1
        addr = self._resolved_address
        alive = addr is not None and gvcp_probe(addr, timeout=min(0.1, max(0.01, deadline - now))) is not None
        if not alive and self.device_id is not None and \
                now - max(self._lost_since, self._last_discovery) >= self.rediscover_s:
            # opened by id and silent at its last address for a while: it may have come back on another
            # IP. A discovery broadcast blocks ~1 s, so it is tried only every `rediscover_s`.
            self._last_discovery = now
            self._resolved_address = None
            alive = True
        if alive:
            try:
                self._open()
                self.counters["reconnects"] += 1
                return True
            except DeviceError as e:
                self.last_error = str(e)
                self._resolved_address = self._resolved_address or addr   # keep probing where it was
        self._backoff.failed()
        return False

    # -- frames --------------------------------------------------------------------------------
    def poll(self, timeout: float) -> Frame | None:
        """Next frame, or None if none arrived within ``timeout`` s (or the camera is reconnecting)."""
        Aravis = load_aravis()
        deadline = time.monotonic() + max(0.0, timeout)
        with self._lock:
            if not self._running:
                raise DeviceError(f"{self.name}: poll() before start()")
            while True:
                if self.state == "lost":
                    raise DeviceError(f"{self.name}: camera lost ({self.last_error}); check power, cable, IP")
                if self.state != "streaming":
                    if not self._try_reconnect(deadline):
                        if time.monotonic() >= deadline:
                            return None
                        continue
                if self._lost.is_set():
                    self._on_lost("control lost (heartbeat timeout)")
                    continue
                remaining = deadline - time.monotonic()
                buf = self._stream.timeout_pop_buffer(max(1, int(remaining * 1e6)))
                arrival = time.monotonic()
                if buf is None:
                    if arrival - self._last_arrival > self._stall_timeout():
                        addr = self._resolved_address
                        if addr is None or gvcp_probe(addr, timeout=0.1) is None:
                            self._on_lost(f"no frames for {arrival - self._last_arrival:.1f} s and no "
                                          "answer to a GVCP probe")
                            continue
                        self.counters["stalls"] += 1
                        self._last_arrival = arrival
                    if arrival >= deadline:
                        return None
                    continue
                try:
                    frame = self._convert(Aravis, buf, arrival)
                finally:
                    self._stream.push_buffer(buf)
                if frame is not None:
                    return frame
                if time.monotonic() >= deadline:
                    return None

    def _stall_timeout(self) -> float:
        if self.req_stall is not None:
            return float(self.req_stall)
        return max(1.0, 10.0 / self.frame_rate_hz) if self.frame_rate_hz > 0 else 2.0

    def _convert(self, Aravis, buf, arrival: float) -> Frame | None:
        status = buf.get_status()
        if status != Aravis.BufferStatus.SUCCESS:
            key = status.value_nick if hasattr(status, "value_nick") else str(status)
            self.bad_status[key] = self.bad_status.get(key, 0) + 1
            self.counters["bad_buffers"] += 1
            return None
        w, h = buf.get_image_width(), buf.get_image_height()
        if (h, w) != (self.height, self.width):
            self.counters["wrong_size"] += 1
            self.last_error = f"buffer is {w}×{h}, expected {self.width}×{self.height}"
            return None
        image = as_uint16_image(buf.get_data(), h, w, self.name)
        ts = int(buf.get_timestamp())
        if ts == 0:                       # camera without a timestamp latch: the host's receive time
            ts = int(buf.get_system_timestamp())
            self.counters["timestamp_fallbacks"] += 1
        self.clock.observe(ts, arrival)
        t = float(self.clock.to_host(ts)) + self.timestamp_offset_s
        outage = self.tracker.last_raw is None and self.tracker.frame_id >= 0
        frame_id, gap = self.tracker.update(buf.get_frame_id())
        if outage and math.isfinite(self._last_t) and self.frame_rate_hz > 0:
            # after a reconnect the device counter restarted: estimate the loss from the time gap
            gap = max(0, round((t - self._last_t) * self.frame_rate_hz) - 1)
            self.counters["outage_frames"] += gap
        self._last_arrival = arrival
        self._last_t = t
        self._recent.append(arrival)
        return Frame(image=image, t=t, frame_id=frame_id, device_ts=ts, arrival=arrival, gap_before=gap,
                     ffc=self._read_ffc())

    def radiometry(self):
        """The camera's Planck constants as a `thermod.physics.radiometry.Planck`, or None.

        Best effort: FLIR GigE cameras expose them as GenICam features ``R`` (integer), ``B``, ``F``,
        ``O`` (float); ``PlanckR`` … are tried too. None when no session is open, a constant is absent
        or unreadable, or the values do not form a valid model (never raises).
        """
        from thermod.physics.radiometry import Planck, RadiometryError

        with self._lock:
            dev = self._device
            if dev is None:
                return None
            values = {}
            for key, names in _PLANCK_FEATURES.items():
                for name in names:
                    v = _safe(lambda name=name: _read_number(dev, name))
                    if v is not None:
                        values[key] = v
                        break
                else:
                    return None
        try:
            return Planck(**values)
        except RadiometryError:
            return None

    def stats(self) -> dict:
        rate = measured_rate_hz(self._recent)
        out = {"state": self.state, "device": self.address or self.device_id, "width": self.width,
               "height": self.height, "pixel_format": self.pixel_format, "frame_rate_hz": self.frame_rate_hz,
               "measured_rate_hz": rate, "packet_size": self.packet_size, "last_error": self.last_error,
               "bad_status": dict(self.bad_status), "ffc_feature": self.ffc_feature, **self.counters,
               **self.tracker.stats()}
        if self.clock is not None:
            out.update(clock_stats(self.clock))
        stream = self._stream
        if stream is not None and hasattr(stream, "get_statistics"):
            st = _safe(stream.get_statistics)
            if st is not None and len(st) == 2:
                out.update(resent_packets=int(st[0]), missing_packets=int(st[1]))
        return out


# GenICam status features that say a flat-field correction (NUC/shutter) is in progress, tried in
# order. FLIR's GigE cores document NUCMode (Off/Automatic/Manual) and the NUCAction command — a mode
# and a trigger, not a status — so there is no standard name; these are the names used for a boolean
# or enumeration status (no camera offering them was at hand to check: pass ffc_feature= for yours).
FFC_STATUS_FEATURES = ("FFCInProgress", "NUCInProgress", "FFCStatus", "NUCStatus", "ShutterStatus")
_FFC_ACTIVE = {"1", "true", "on", "active", "inprogress", "in_progress", "running", "busy", "closed"}


def ffc_value(value: str) -> bool:
    """Whether a status feature's value (as a string: boolean, integer or enumeration entry) means a
    flat-field correction is in progress: 1/true/on, InProgress, Active, Running, Busy, shutter Closed."""
    return str(value).strip().lower() in _FFC_ACTIVE


def _set_feature(dev, key: str, value, name: str) -> None:
    if not dev.is_feature_available(key):
        raise DeviceError(f"{name}: GenICam feature {key!r} not available on this camera")
    if isinstance(value, bool):
        dev.set_boolean_feature_value(key, value)
    elif isinstance(value, int):
        dev.set_integer_feature_value(key, value)
    elif isinstance(value, float):
        dev.set_float_feature_value(key, value)
    else:
        dev.set_string_feature_value(key, str(value))


# GenICam names of the Planck constants, first match wins (FLIR A-series/Ax5 over eBUS/Aravis: R, B, F, O)
_PLANCK_FEATURES = {"R": ("R", "PlanckR"), "B": ("B", "PlanckB"), "F": ("F", "PlanckF"),
                    "O": ("O", "PlanckO")}


def _read_number(dev, key: str) -> float | None:
    """A numeric feature's value (integer or float node), None when the camera has no such feature."""
    if not dev.is_feature_available(key):
        return None
    v = _safe(lambda: dev.get_float_feature_value(key))
    if v is None:
        v = dev.get_integer_feature_value(key)
    return float(v)


def _msg(e: Exception) -> str:
    return getattr(e, "message", None) or str(e)


def _release_lost(session: list, lost: threading.Event) -> None:
    """Release a lost camera's session ([camera, stream, device]) so that its last reference never
    falls inside the heartbeat thread's control-lost emission: the emission holds a reference of its
    own, and the device finalized there would join the heartbeat thread from itself (GLib error,
    SIGTRAP; the race Aravis issue #50 describes for streams). Leaving control first stops new
    heartbeat checks from emitting; one already under way emits within `LAST_CONTROL_LOST_S`."""
    leave = getattr(session[2], "leave_control", None)      # a GigE Vision device's
    if leave is not None and not lost.is_set():
        _safe(leave)
        lost.wait(LAST_CONTROL_LOST_S)
    if lost.is_set():
        time.sleep(0.2)       # the emission that set it returns through Aravis after our handler
    session.clear()


def _safe(fn):
    try:
        return fn()
    except Exception:
        return None
