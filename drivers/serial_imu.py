"""Serial (UART / USB-serial) gyro: a framed binary protocol, resynchronising on garbage.

Wire protocol "thermod serial IMU v1" (little-endian; the byte table: docs/design.md §5, "Gyro
sources"): sync 0xA5 0x5A, payload length, type (1: rates as 3 × float32 rad/s; 2: 3 × int16 times
a float32 scale), a uint32 sample counter, a uint32 µs device time, the rates in the gyro frame,
and a CRC-16/CCITT-FALSE over length, type and payload.

The rules it keeps: a frame is accepted only when its CRC matches; after a bad CRC
(``crc_errors``) the search for the next sync resumes one byte after the rejected sync, so a
corrupted length cannot swallow good frames. Other bytes count as ``garbage_bytes``; rates that are
NaN, infinite or beyond ``max_rate_rad_s`` are dropped as ``invalid``; gaps in ``seq`` are lost
frames (``gap_before``, ``n_lost``); device counters that cannot follow each other start a new
epoch (``resets``). Sample times are the unwrapped device µs mapped to host time by
:class:`thermod.io.clock.ClockMapper`. The port is a path or ``usb:VID:PID[:SERIAL]`` (resolved by
:mod:`thermod.drivers.usb_lookup` at every (re)open); FTDI low-latency mode is requested where
supported. A disconnect raises :class:`SerialIMUError` once; later polls try to reopen the port
(every ``reopen_interval_s``) and resume with a gap when the device is back.
"""

from __future__ import annotations

import math
import struct
import time

import numpy as np

from thermod.drivers.gyro_base import GyroBatch, GyroDeviceError, GyroSource
from thermod.errors import DeviceError
from thermod.io.clock import ClockMapper

SYNC = b"\xa5\x5a"
TYPE_F32, TYPE_I16 = 1, 2
PAYLOAD_LEN = {TYPE_F32: 20, TYPE_I16: 18}
HEADER = 4           # sync, length, type
CRC_LEN = 2
MAX_FRAME = HEADER + max(PAYLOAD_LEN.values()) + CRC_LEN


def _crc_table() -> list[int]:
    table = []
    for b in range(256):
        c = b << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    t = _CRC_TABLE
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ b]
    return crc


def encode_frame(seq: int, t_us: int, rate, *, int16_scale: float | None = None) -> bytes:
    """One frame of the protocol (used by the emulator and handy for firmware test vectors)."""
    if int16_scale is None:
        body = struct.pack("<BBII3f", PAYLOAD_LEN[TYPE_F32], TYPE_F32, seq & 0xFFFFFFFF, t_us & 0xFFFFFFFF,
                           *(float(x) for x in rate))
    else:
        q = [int(max(-32768, min(32767, round(float(x) / int16_scale)))) for x in rate]
        body = struct.pack("<BBII3hf", PAYLOAD_LEN[TYPE_I16], TYPE_I16, seq & 0xFFFFFFFF, t_us & 0xFFFFFFFF,
                           *q, int16_scale)
    return SYNC + body + struct.pack("<H", crc16_ccitt(body))


MAX_RATE_RAD_S = math.radians(4000.0)   # the widest full scale of MEMS gyros (ICM-45686: ±4000 °/s)


class FrameParser:
    """Incremental frame parser: ``feed(bytes)`` → list of (seq32, t_us32, rate[3]) of good frames.

    A frame whose CRC matches but whose rates cannot be a gyro reading (NaN, ±inf, beyond
    ``max_rate_rad_s``, or a type-2 scale that is not a positive finite number) is dropped and
    counted in ``invalid_rates``; its seq then shows as lost.
    """

    def __init__(self, max_rate_rad_s: float = MAX_RATE_RAD_S):
        self.buf = bytearray()
        self.max_rate = float(max_rate_rad_s)
        self.crc_errors = 0
        self.garbage_bytes = 0
        self.invalid_rates = 0
        self.frames = 0

    def feed(self, data: bytes) -> list[tuple[int, int, tuple[float, float, float]]]:
        buf = self.buf
        buf += data
        out = []
        i = 0
        n = len(buf)
        while True:
            j = buf.find(SYNC, i)
            if j < 0:
                # keep a trailing 0xA5: it may be the first half of the next sync
                keep = 1 if n > i and buf[-1] == SYNC[0] else 0
                self.garbage_bytes += n - i - keep
                i = n - keep
                break
            self.garbage_bytes += j - i
            i = j
            if n - i < HEADER:
                break
            length, ftype = buf[i + 2], buf[i + 3]
            if PAYLOAD_LEN.get(ftype) != length:
                self.garbage_bytes += 1                  # not a frame start: resync past this byte
                i += 1
                continue
            end = i + HEADER + length + CRC_LEN
            if n < end:
                break
            body = bytes(buf[i + 2:end - CRC_LEN])
            if crc16_ccitt(body) != buf[end - 2] | (buf[end - 1] << 8):
                self.crc_errors += 1
                i += 1                                   # the next sync may lie inside this frame
                continue
            i = end
            if ftype == TYPE_F32:
                _, _, seq, t_us, x, y, z = struct.unpack("<BBII3f", body)
                ok = True
            else:
                _, _, seq, t_us, qx, qy, qz, scale = struct.unpack("<BBII3hf", body)
                ok = math.isfinite(scale) and scale > 0
                x, y, z = qx * scale, qy * scale, qz * scale
            # NaN fails every comparison, so "not within range" also catches it
            if not (ok and abs(x) <= self.max_rate and abs(y) <= self.max_rate and abs(z) <= self.max_rate):
                self.invalid_rates += 1
                continue
            out.append((seq, t_us, (x, y, z)))
            self.frames += 1
        del buf[:i]
        return out


class SerialIMUError(GyroDeviceError):
    """Serial IMU open, disconnect or read failure."""


class SerialIMU(GyroSource):
    """Gyro source for the serial protocol above.

    Parameters
    ----------
    port
        Device path (prefer /dev/serial/by-id/…) or ``usb:VID:PID[:SERIAL]`` (hex ids).
    baud
        921600 carries 1 kHz type-1 frames (26 B) with 2.7× headroom.
    rate_hz
        Nominal sample rate (for lost-sample estimates across reconnects).
    sysfs_root, dev_root
        For ``usb:`` lookup (tests point them at a fake tree).
    """

    def __init__(self, port: str, *, baud: int = 921600, rate_hz: float = 1000.0, low_latency: bool = True,
                 reopen_interval_s: float = 0.2, clock_window_s: float = 20.0, name: str | None = None,
                 sysfs_root: str = "/sys", dev_root: str = "/dev", max_rate_rad_s: float = MAX_RATE_RAD_S):
        super().__init__()
        self.port_spec = port
        self.baud = int(baud)
        self.rate_hz = float(rate_hz)
        self.low_latency = low_latency
        self.reopen_interval_s = reopen_interval_s
        self.name = name or f"serial IMU {port}"
        self._sysfs_root, self._dev_root = sysfs_root, dev_root
        self.clock = ClockMapper(1e-6, window_s=clock_window_s, name=self.name)
        self._ser = None
        self._parser = FrameParser(max_rate_rad_s)
        self._running = False
        self._connected = False
        self._next_reopen = 0.0
        self._seq_last: int | None = None      # unwrapped
        self._seq_raw_last = 0
        self._tus_last: int | None = None      # unwrapped device µs
        self._tus_raw_last = 0
        self._t_host_last = float("nan")
        self._gap_pending = False
        self._lost_pending = 0
        self._t_out = -float("inf")            # newest time stamp handed out
        self._queue: list[GyroBatch] = []      # batches split off a read at lost frames
        self._stats.update(garbage_bytes=0, frames=0, invalid=0, reconnects=0, disconnects=0, low_latency=0,
                           connected=0)

    # -- port handling ---------------------------------------------------------------------------
    def _resolve(self) -> str:
        if self.port_spec.startswith("usb:"):
            from thermod.drivers.usb_lookup import find_tty, parse_usb_spec
            vid, pid, serial_no = parse_usb_spec(self.port_spec)
            return find_tty(vid, pid, serial_no, sysfs_root=self._sysfs_root, dev_root=self._dev_root)
        return self.port_spec

    def _open(self) -> None:
        import serial
        try:
            path = self._resolve()
        except DeviceError as e:
            raise SerialIMUError(f"{self.name}: {e}") from e
        try:
            ser = serial.Serial(path, self.baud, timeout=0, exclusive=True)
        except (serial.SerialException, OSError) as e:
            raise SerialIMUError(f"{self.name}: cannot open {path}: {e} — check the cable, the by-id path "
                                 "(ls -l /dev/serial/by-id) and that you are in group dialout") from e
        if self.low_latency:
            try:
                ser.set_low_latency_mode(True)
                self._stats["low_latency"] = 1
            except (AttributeError, ValueError, OSError, serial.SerialException):
                self._stats["low_latency"] = 0           # not an FTDI/serial-core port (pty, CDC-ACM)
        ser.reset_input_buffer()
        self._ser = ser
        self._parser.buf.clear()                         # a partial frame from before the reopen
        self._connected = True
        self._stats["connected"] = 1

    def _close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # noqa: BLE001 - a vanished device may fail to close; it is gone either way
                pass
        self._ser = None
        self._connected = False
        self._stats["connected"] = 0

    def start(self) -> None:
        self._open()
        self._running = True

    def stop(self) -> None:
        self._running = False
        self._close()

    # -- reading ---------------------------------------------------------------------------------
    def poll(self, timeout: float) -> GyroBatch | None:
        import serial
        if not self._running:
            raise SerialIMUError(f"{self.name}: poll() before start()")
        if self._queue:
            return self._count_batch(self._queue.pop(0))
        deadline = time.monotonic() + max(0.0, timeout)
        if not self._connected:
            now = time.monotonic()
            if now < self._next_reopen:
                time.sleep(max(0.0, min(deadline, self._next_reopen) - now))
                return None
            try:
                self._open()
            except SerialIMUError:
                self._next_reopen = time.monotonic() + self.reopen_interval_s
                time.sleep(max(0.0, min(deadline - time.monotonic(), self.reopen_interval_s)))
                return None
            self._stats["reconnects"] += 1
            self._gap_pending = True
        while True:
            try:
                self._ser.timeout = max(0.0, deadline - time.monotonic())
                data = self._ser.read(max(1, self._ser.in_waiting))
                if self._ser.in_waiting:
                    data += self._ser.read(self._ser.in_waiting)
            except (serial.SerialException, OSError) as e:
                self._close()
                self._stats["disconnects"] += 1
                self._stats["io_errors"] += 1
                self._next_reopen = time.monotonic() + self.reopen_interval_s
                raise SerialIMUError(f"{self.name}: device disconnected or read failed ({e}); will reopen "
                                     f"{self.port_spec} when it comes back — check the cable / USB hub"
                                     ) from e
            t_arrival = time.monotonic()
            frames = self._parser.feed(data) if data else []
            self._stats["crc_errors"] = self._parser.crc_errors
            self._stats["garbage_bytes"] = self._parser.garbage_bytes
            self._stats["frames"] = self._parser.frames
            self._stats["invalid"] = self._parser.invalid_rates
            if frames:
                self._queue.extend(self._batches(frames, t_arrival))
                return self._count_batch(self._queue.pop(0))
            if time.monotonic() >= deadline:
                return None

    def _consistent(self, dseq, dtus):
        """Whether steps of the two device counters (mod 2**32) can follow each other: both forward,
        and the time step within 4× (plus 0.1 s) of what the sample step takes at ``rate_hz``."""
        period_us = 1e6 / self.rate_hz
        return ((dseq >= 1) & (dseq < 2**31) & (dtus >= 1) & (dtus < 2**31)
                & (dtus <= 4 * dseq * period_us + 1e5) & (4 * dtus >= dseq * period_us - 4e5))

    def _batches(self, frames, t_arrival: float) -> list[GyroBatch]:
        seq32 = np.array([f[0] for f in frames], np.int64)
        tus32 = np.array([f[1] for f in frames], np.int64)
        # a reboot, or a counter that jumped, inside this read: each run of consistent frames is
        # checked against the one before it (and becomes its own epoch)
        broken = (np.flatnonzero(~self._consistent(np.diff(seq32) & 0xFFFFFFFF, np.diff(tus32) & 0xFFFFFFFF))
                  + 1).tolist()
        out = []
        for a, b in zip([0, *broken], [*broken, len(frames)], strict=True):
            out += self._run_batches(frames[a:b], seq32[a:b], tus32[a:b], t_arrival)
        return out

    def _run_batches(self, frames, seq32: np.ndarray, tus32: np.ndarray, t_arrival: float) -> list[GyroBatch]:
        """Batches of frames whose counters follow each other (one run of a read)."""
        rate = np.array([f[2] for f in frames], np.float32).reshape(-1, 3)
        gap, lost = self._gap_pending, self._lost_pending
        if self._seq_last is None:
            seq0 = int(seq32[0])
            tus0 = int(tus32[0])
        else:
            dseq = (int(seq32[0]) - self._seq_raw_last) & 0xFFFFFFFF
            dtus = (int(tus32[0]) - self._tus_raw_last) & 0xFFFFFFFF
            elapsed_us = (t_arrival - self._t_host_last) * 1e6
            if not self._consistent(dseq, dtus) or dtus > 4 * elapsed_us + 1e6:
                # the device restarted or a counter jumped (back, or further than host time allows):
                # new epoch, keep counting
                self._stats["resets"] += 1
                # samples since the newest one handed out (mapped time) minus those in this read
                est = max(1, int(round((t_arrival - self._t_out) * self.rate_hz)) - len(frames) + 1)
                seq0 = self._seq_last + est
                tus0 = self._tus_last + int(est * 1e6 / self.rate_hz)
                gap, lost = True, lost + est - 1
                self.clock.restart()
            else:
                seq0 = self._seq_last + dseq
                tus0 = self._tus_last + dtus
                if dseq > 1:
                    gap, lost = True, lost + dseq - 1
        # unwrap within the read relative to its first frame
        seq = seq0 + ((seq32 - seq32[0]) & 0xFFFFFFFF)
        tus = tus0 + ((tus32 - tus32[0]) & 0xFFFFFFFF)
        self._seq_last, self._seq_raw_last = int(seq[-1]), int(seq32[-1])
        self._tus_last, self._tus_raw_last = int(tus[-1]), int(tus32[-1])
        self._t_host_last = t_arrival
        self.clock.observe(int(tus[-1]), t_arrival)
        t = np.asarray(self.clock.to_host(tus), np.float64)
        if t[0] <= self._t_out:
            # the fit lowered its offset (start-up, after a gap): keep sample times strictly increasing
            t = np.maximum(t, self._t_out + 0.5 / self.rate_hz * np.arange(1, len(t) + 1))
        self._t_out = float(t[-1])
        self._gap_pending, self._lost_pending = False, 0
        # lost frames inside the read split it, so that gap_before says exactly where samples are missing
        cuts = np.flatnonzero(np.diff(seq) != 1) + 1
        bounds = [0, *cuts.tolist(), len(seq)]
        batches = []
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            if a == 0:
                g, n_lost = gap, lost
            else:
                g, n_lost = True, int(seq[a] - seq[a - 1] - 1)
            batches.append(GyroBatch(t=t[a:b], rate=rate[a:b], seq=int(seq[a]), gap_before=g, n_lost=n_lost))
        return batches


SerialGyro = SerialIMU      # the name thermod.runtime.daemon builds "serial" gyro sources with
