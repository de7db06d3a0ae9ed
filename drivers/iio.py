"""Linux Industrial I/O (IIO) gyro through the buffered interface.

The kernel driver of the chip (``inv_icm42600``, ``bmi160``, ``adis16xxx``, …) owns the FIFO; we
find the device by its ``name`` under ``/sys/bus/iio/devices``, enable the angular-velocity scan
elements (and the timestamp) on the ``monotonic`` clock, size and enable the buffer, and read
fixed-size records from ``/dev/iio:deviceN`` in the layout of the kernel's sysfs-bus-iio ABI.

Timing: samples are counted (sequence = device clock) and mapped to host time by
:class:`thermod.io.clock.ClockMapper`, fed with the kernel timestamp of the newest sample of each
read or, without a timestamp channel, the time the read returned. A hole in the timestamps is a
loss (``gap_before``, ``n_lost``); a stamp that cannot be a sample time or a hole longer than host
time allows starts a new epoch (``resets``), and a lost count is never more than host time allows.
Both roots are injectable (``sysfs_root``, ``dev_path``) so the emulator in ``thermod.sim.emu_iio``
runs this exact code on a temp directory and a FIFO. Record layout and epochs in full:
docs/design.md §5, "Gyro sources".
"""

from __future__ import annotations

import math
import os
import re
import select
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thermod.drivers.gyro_base import GyroBatch, GyroDeviceError, GyroSource
from thermod.io.clock import ClockMapper

TYPE_RE = re.compile(r"^(be|le):([su])(\d{1,3})/(\d{1,3})(?:X(\d{1,3}))?>>(\d{1,3})$", re.ASCII)
AXES = ("x", "y", "z")


class IIOError(GyroDeviceError):
    """IIO device lookup, configuration or read failure."""


@dataclass(frozen=True)
class ScanType:
    """One parsed ``*_type`` string."""

    big_endian: bool
    signed: bool
    bits: int
    storage_bits: int
    repeat: int
    shift: int

    @property
    def nbytes(self) -> int:
        return self.storage_bits // 8 * self.repeat

    @property
    def align(self) -> int:
        return self.storage_bits // 8


def parse_type(text: str, where: str = "*_type") -> ScanType:
    """Parse ``le:s16/16>>0``, ``be:u12/16>>4``, ``le:s16/16X3>>0`` …"""
    m = TYPE_RE.match(text.strip())
    if not m:
        raise IIOError(f"{where}: cannot parse scan type {text.strip()!r}, expected e.g. 'le:s16/16>>0'")
    end, sign, bits, storage, rep, shift = m.groups()
    st = ScanType(end == "be", sign == "s", int(bits), int(storage), int(rep or 1), int(shift))
    if st.storage_bits not in (8, 16, 32, 64) or not 0 < st.bits <= st.storage_bits - st.shift:
        raise IIOError(f"{where}: scan type {text.strip()!r} is inconsistent (bits + shift must fit the "
                       "8/16/32/64-bit storage)")
    if not 1 <= st.repeat <= 64:
        raise IIOError(f"{where}: scan type {text.strip()!r} repeats {st.repeat} times, expected 1 to 64")
    return st


@dataclass(frozen=True)
class Channel:
    name: str          # scan element name, e.g. "in_anglvel_x"
    index: int
    type: ScanType
    offset: int        # byte offset in the record


def layout(channels: list[tuple[str, int, ScanType]]) -> tuple[list[Channel], int]:
    """Byte offsets of the enabled channels and the record size (IIO alignment rules)."""
    out, off, biggest = [], 0, 1
    for name, index, st in sorted(channels, key=lambda c: c[1]):
        off = -(-off // st.align) * st.align
        out.append(Channel(name, index, st, off))
        off += st.nbytes
        biggest = max(biggest, st.align)
    return out, -(-off // biggest) * biggest


def extract(records: np.ndarray, ch: Channel) -> np.ndarray:
    """int64 [n, repeat] values of one channel from uint8 records [n, record_size]."""
    st = ch.type
    size = st.storage_bits // 8
    kind = {1: "u1", 2: "u2", 4: "u4", 8: "u8"}[size]
    dt = np.dtype(kind).newbyteorder(">" if st.big_endian else "<")
    raw = np.ascontiguousarray(records[:, ch.offset:ch.offset + size * st.repeat])
    words = raw.view(dt).astype(np.uint64)
    words = words >> np.uint64(st.shift)
    if st.bits < 64:
        words = words & np.uint64((1 << st.bits) - 1)
    vals = words.astype(np.int64) if st.bits < 64 else words.view(np.int64)
    if st.signed and st.bits < 64:
        vals = np.where(vals >= (1 << (st.bits - 1)), vals - (1 << st.bits), vals)
    return vals.reshape(len(records), st.repeat)


def find_device(name: str, sysfs_root: str | os.PathLike = "/sys/bus/iio/devices") -> Path:
    """The ``iio:deviceN`` directory whose ``name`` file reads ``name``."""
    root = Path(sysfs_root)
    seen = []
    for d in sorted(root.glob("iio:device*")):
        try:
            n = (d / "name").read_text().strip()
        except OSError:
            continue
        seen.append(f"{d.name}={n}")
        if n == name:
            return d
    raise IIOError(f"IIO device named {name!r} not found under {root} (present: {', '.join(seen) or 'none'}) "
                   "— check that the kernel driver is loaded (dmesg, device tree overlay)")


class IIOGyro(GyroSource):
    """Gyro source on a Linux IIO buffered device.

    Parameters
    ----------
    device
        The IIO ``name`` (e.g. "icm42688"), or a path to the ``iio:deviceN`` sysfs directory.
    rate_hz
        Sampling frequency; written to ``in_anglvel_sampling_frequency`` / ``sampling_frequency``
        when present and read back.
    buffer_length
        Kernel buffer length in records (``buffer/length``).
    sysfs_root, dev_path
        Where to look for devices, and the character device to read (default ``/dev/iio:deviceN``).
    """

    def __init__(self, device: str, *, rate_hz: float = 1000.0, buffer_length: int = 256,
                 sysfs_root: str | os.PathLike = "/sys/bus/iio/devices", dev_path: str | None = None,
                 timestamp: bool = True, clock_window_s: float = 20.0, name: str | None = None):
        super().__init__()
        self.device = device
        self.rate_hz = float(rate_hz)
        self.buffer_length = int(buffer_length)
        self.sysfs_root = Path(sysfs_root)
        self._dev_path = dev_path
        self.use_timestamp = timestamp
        self.name = name or f"IIO {device}"
        self.clock = ClockMapper(1.0 / self.rate_hz, window_s=clock_window_s, name=self.name)
        self._fd = -1
        self._pending = b""
        self._seq = 0
        self._t_out = -float("inf")
        self._t_enabled = -float("inf")
        self._last_tns: int | None = None      # newest usable kernel time stamp (ns)
        self._after_ref = 0                     # records read since that stamp
        self._bad_stamps = False                # the newest stamp was not a sample time
        self._queue: list[GyroBatch] = []
        self._running = False
        self.channels: list[Channel] = []
        self.record_size = 0
        self._stats.update(bytes=0, timestamp=0)

    # -- sysfs -----------------------------------------------------------------------------------
    def _path(self, rel: str) -> Path:
        return self.dir / rel

    def _read(self, rel: str) -> str:
        try:
            return self._path(rel).read_text().strip()
        except OSError as e:
            raise IIOError(f"{self.name}: cannot read {self._path(rel)}: {e.strerror or e}") from e

    def _write(self, rel: str, value) -> None:
        try:
            self._path(rel).write_text(f"{value}\n")
        except OSError as e:
            raise IIOError(f"{self.name}: cannot write {value!r} to {self._path(rel)}: {e.strerror or e} — "
                           "check permissions (udev rule for the iio group) and that the buffer is "
                           "disabled") from e

    def start(self) -> None:
        p = Path(self.device)
        self.dir = p if p.is_dir() and (p / "name").exists() else find_device(self.device, self.sysfs_root)
        self.name = f"IIO {self._read('name')} ({self.dir.name})"
        self.clock.name = self.name
        if self._read("buffer/enable") != "0":
            self._write("buffer/enable", 0)          # another reader left it on: we own it now
        scan = self.dir / "scan_elements"
        if not scan.is_dir():
            raise IIOError(f"{self.name}: {scan} missing — the driver has no buffered (triggered) support")
        want = {f"in_anglvel_{a}" for a in AXES}
        if self.use_timestamp and (scan / "in_timestamp_en").exists():
            want.add("in_timestamp")
        missing = [w for w in sorted(want) if not (scan / f"{w}_en").exists()]
        if missing:
            raise IIOError(f"{self.name}: scan elements {missing} missing in {scan} — not a gyro?")
        for en in sorted(scan.glob("*_en")):
            self._write(f"scan_elements/{en.name}", 1 if en.name[:-3] in want else 0)
        chans = []
        for w in sorted(want):
            st = parse_type(self._read(f"scan_elements/{w}_type"), str(scan / f"{w}_type"))
            if self._read(f"scan_elements/{w}_en") != "1":
                raise IIOError(f"{self.name}: {w}_en did not stay enabled")
            chans.append((w, int(self._read(f"scan_elements/{w}_index")), st))
        self.channels, self.record_size = layout(chans)
        self._by_name = {c.name: c for c in self.channels}
        self._stats["timestamp"] = int("in_timestamp" in self._by_name)
        self.scale = np.array([self._scale(a) for a in AXES], np.float64)
        if (self.dir / "current_timestamp_clock").exists():
            self._write("current_timestamp_clock", "monotonic")
            if self._read("current_timestamp_clock") != "monotonic":
                raise IIOError(f"{self.name}: current_timestamp_clock did not accept 'monotonic'")
        for f in ("in_anglvel_sampling_frequency", "sampling_frequency"):
            if (self.dir / f).exists():
                self._write(f, f"{self.rate_hz:g}")
                got = float(self._read(f))
                if abs(got - self.rate_hz) > 1e-6 * self.rate_hz:
                    raise IIOError(f"{self.name}: {f} read back {got:g}, expected {self.rate_hz:g} — pick a "
                                   f"rate from {f.replace('frequency', 'frequency_available')}")
                break
        self._write("buffer/length", self.buffer_length)
        dev = self._dev_path or f"/dev/{self.dir.name}"
        try:
            self._fd = os.open(dev, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as e:
            raise IIOError(f"{self.name}: cannot open {dev}: {e.strerror or e} — check permissions "
                           "(udev rule) and that no other process holds the buffer") from e
        self._t_enabled = time.monotonic()
        self._write("buffer/enable", 1)               # last: the layout is frozen from here on
        self._running = True

    def _scale(self, axis: str) -> float:
        for f in (f"in_anglvel_{axis}_scale", "in_anglvel_scale"):
            if (self.dir / f).exists():
                try:
                    scale = float(self._read(f))
                except ValueError as e:
                    raise IIOError(f"{self.name}: {self.dir / f} is not a number") from e
                if not (math.isfinite(scale) and scale > 0):
                    raise IIOError(f"{self.name}: {self.dir / f} reads {scale!r}, expected a positive "
                                   "finite rad/s per LSB")
                return scale
        raise IIOError(f"{self.name}: no in_anglvel_scale in {self.dir}")

    def stop(self) -> None:
        if self._running:
            self._running = False
            try:
                self._write("buffer/enable", 0)
            except IIOError:
                pass                                   # device gone: nothing to disable
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    # -- reading ---------------------------------------------------------------------------------
    def poll(self, timeout: float) -> GyroBatch | None:
        if not self._running:
            raise IIOError(f"{self.name}: poll() before start()")
        if self._queue:
            return self._count_batch(self._queue.pop(0))
        try:
            r, _, _ = select.select([self._fd], [], [], max(0.0, timeout))
            if not r:
                return None
            data = os.read(self._fd, self.record_size * self.buffer_length)
        except BlockingIOError:
            return None
        except OSError as e:
            self._stats["io_errors"] += 1
            raise IIOError(f"{self.name}: read failed: {e.strerror or e} — device removed or buffer disabled "
                           "by another process") from e
        t_arrival = time.monotonic()
        if not data:
            time.sleep(min(timeout, 0.001))            # writer side closed (emulator restart): no busy loop
            return None
        return self._ingest(data, t_arrival)

    def _ingest(self, data: bytes, t_arrival: float) -> GyroBatch | None:
        """Decode the bytes of one read that returned at ``t_arrival``: the first batch, the rest queued."""
        self._stats["bytes"] += len(data)
        buf = self._pending + data
        n = len(buf) // self.record_size
        self._pending = buf[n * self.record_size:]
        if n == 0:
            return None
        rec = np.frombuffer(buf[: n * self.record_size], np.uint8).reshape(n, self.record_size)
        raw = np.concatenate([extract(rec, self._by_name[f"in_anglvel_{a}"])[:, :1] for a in AXES], axis=1)
        rate = (raw * self.scale).astype(np.float32)
        ts = self._by_name.get("in_timestamp")
        if ts is None:
            return self._count_batch(self._emit(np.arange(n), rate, t_arrival, 0, False))
        tns = extract(rec, ts)[:, 0].tolist()
        batches = []
        for a, b, lost, epoch, stamped in self._segments(tns, t_arrival):
            t_obs = tns[b - 1] * 1e-9 if stamped else t_arrival
            batches.append(self._emit(np.arange(b - a), rate[a:b], t_obs, lost, epoch))
        self._queue.extend(batches[1:])
        return self._count_batch(batches[0])

    def _future_slack_ns(self) -> float:
        # a kernel stamp is taken before the read returns; interpolating drivers may run a little ahead
        return max(0.01, 4.0 / self.rate_hz) * 1e9

    def _segments(self, tns: list[int], t_arrival: float) -> list[tuple[int, int, int, bool, bool]]:
        """Split one read's records by their kernel time stamps: [(start, end, lost before, new epoch,
        the last record's stamp is good)].

        A hole (the full kernel buffer dropped records) shows as a forward step of the stamps. A stamp
        that cannot be a CLOCK_MONOTONIC sample time (zero or negative, before the buffer was
        enabled, later than the read that returned it, or more than a period before the newest good
        stamp) starts an epoch; its records are timed by the read, as without a timestamp channel,
        until the stamps make sense again. A hole longer than the host time since the last sample
        handed out allows starts an epoch too, with the lost count estimated from host time: never
        more samples than could have been taken.
        """
        rate = self.rate_hz
        future = t_arrival * 1e9 + self._future_slack_ns()
        past = self._t_enabled * 1e9 - self._future_slack_ns()    # no record predates the buffer
        back_tol = 1e9 / rate
        n = len(tns)
        since = (t_arrival - max(self._t_out, self._t_enabled)) * rate
        budget = since + max(2.0, 0.02 * rate)      # mapping error of the newest sample handed out
        ref, after_ref, bad = self._last_tns, self._after_ref, self._bad_stamps
        used = 0                                     # samples (records and holes) since then
        segs: list[list] = []
        for i, ts in enumerate(tns):
            lost, epoch = 0, False
            if ts < past or ts > future or (ref is not None and ts < ref - back_tol):
                epoch, bad = not bad, True           # the first of a run of bad stamps
                after_ref += 1
            else:
                if ref is not None:
                    lost = max(0, round((ts - ref) * 1e-9 * rate) - 1 - after_ref)
                    if used + lost + 1 > budget:
                        epoch = True
                        lost = max(0, round(since) - used - (n - i))
                ref, after_ref, bad = ts, 0, False
            if i == 0 or lost or epoch:
                segs.append([i, i + 1, lost, epoch, not bad])
            else:
                segs[-1][1], segs[-1][4] = i + 1, not bad
            used += lost + 1
        self._last_tns, self._after_ref, self._bad_stamps = ref, after_ref, bad
        return [tuple(s) for s in segs]

    def _emit(self, offs: np.ndarray, rate: np.ndarray, t_obs: float, lost: int, epoch: bool) -> GyroBatch:
        """A batch of consecutive samples (sample offsets ``offs``), ``lost`` samples missing before it;
        ``epoch``: the time base changed before it, so the clock fit restarts."""
        if epoch:
            self._stats["resets"] += 1
            self.clock.restart()
        seq0 = self._seq + lost
        self._seq = seq0 + int(offs[-1]) + 1
        self.clock.observe(self._seq - 1, t_obs)   # newest sample: kernel IRQ time, or read time
        t = np.asarray(self.clock.to_host(seq0 + offs), np.float64)
        if t[0] <= self._t_out:
            t = np.maximum(t, self._t_out + 0.5 / self.rate_hz * np.arange(1, len(t) + 1))
        self._t_out = float(t[-1])
        return GyroBatch(t=t, rate=rate, seq=seq0, gap_before=lost > 0 or epoch, n_lost=lost)
