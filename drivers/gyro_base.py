"""Gyro source contract shared by every gyro driver (docs/interfaces.md, "Devices")."""

from __future__ import annotations

import math
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from thermod.errors import DeviceError
from thermod.io.clock import ClockMapper


@dataclass
class GyroBatch:
    """Consecutive raw gyro samples.

    Attributes
    ----------
    t : float64 [n]
        Host CLOCK_MONOTONIC seconds of each sample, mapped from the device counter by
        :class:`thermod.io.clock.ClockMapper` (never the read time).
    rate : float32 [n, 3]
        Raw angular rate in rad/s, gyro frame (uncalibrated; docs/design.md §2).
    seq : int
        Device sample index of the first sample (unwrapped, counts lost samples too).
    gap_before : bool
        Samples were lost just before this batch (FIFO overflow, dropped frame, reconnect).
    n_lost : int
        Best estimate of how many (0 when unknown or none).
    """

    t: np.ndarray
    rate: np.ndarray
    seq: int
    gap_before: bool = False
    n_lost: int = 0

    def __len__(self) -> int:
        return len(self.t)


class GyroSource:
    """Base class of gyro drivers. The daemon's driver thread calls :meth:`poll` in a loop.

    Subclasses implement ``start``, ``stop`` and ``poll``; counters live in ``self._stats`` and are
    returned (copied) by :meth:`stats`. Every source offers ``name``, ``clock`` (its device-clock
    mapping, or None when its times need none, e.g. a replay) and ``stats()``.
    """

    name: str = "gyro"
    clock: ClockMapper | None = None     # device clock → host mapping, if the driver fits one

    def __init__(self) -> None:
        self._stats: dict[str, float] = {"samples": 0, "batches": 0, "overflows": 0, "gaps": 0,
                                         "lost": 0, "crc_errors": 0, "io_errors": 0, "resets": 0}

    def start(self) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError

    def poll(self, timeout: float) -> GyroBatch | None:
        """Return the samples read since the last call, blocking at most ``timeout`` s (None if none)."""
        raise NotImplementedError

    def stats(self) -> dict:
        """Counters: samples, batches, overflows, gaps, lost, crc_errors, io_errors, resets, …"""
        return dict(self._stats)

    def _count_batch(self, batch: GyroBatch) -> GyroBatch:
        self._stats["samples"] += len(batch)
        self._stats["batches"] += 1
        if batch.gap_before:
            self._stats["gaps"] += 1
            self._stats["lost"] += batch.n_lost
        return batch

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class GyroDeviceError(DeviceError):
    """A gyro driver's I/O or identification failure; each driver raises its own subclass."""


READ_INTERVAL_MAX_S = 0.025


class FifoGyro(GyroSource):
    """Common FIFO-reading loop of the register-chip drivers (ICM-42688-P, MPU-6000/6050, BMI088).

    A subclass supplies the register map and ``_identify``, ``_configure``, ``_fifo_status``,
    ``_flush``, ``_read_fifo`` and ``_decode``. This class owns the timing: read the FIFO every
    ``read_interval_s`` (and at once when a reader asks, `request_read`), count samples (the unwrapped
    sequence number is the device clock), map ``seq × period`` to host time with
    :class:`thermod.io.clock.ClockMapper` fed with the time taken right after the FIFO count was read
    (every counted sample existed by then), flush and mark a gap on overflow or an impossible FIFO count
    (``overflows``, ``bad_counts``), and after an I/O error (a NACK, a short transfer: ``io_errors``,
    raised once as the driver's DeviceError) re-identify, re-configure and flush before reading again (a
    replugged chip has lost its configuration).
    """

    chip = "gyro"
    error_type: type[GyroDeviceError] = GyroDeviceError
    fifo_size = 1024
    full_scales_dps: tuple[float, ...] = ()

    def __init__(self, bus, *, full_scale_dps: float, rate_hz: float = 1000.0,
                 read_interval_s: float | None = None, clock_window_s: float = 20.0, name: str | None = None):
        super().__init__()
        if full_scale_dps not in self.full_scales_dps:
            raise self.error_type(f"{self.chip}: full_scale_dps={full_scale_dps!r} is not supported, "
                                  f"expected one of {list(self.full_scales_dps)}")
        self.bus = bus
        self.name = name or f"{self.chip} ({bus.describe()})"
        self.full_scale_dps = float(full_scale_dps)
        self.rate_hz = float(rate_hz)
        self._read_interval_s = None if read_interval_s is None else float(read_interval_s)
        self.clock_window_s = float(clock_window_s)
        # rad/s per LSB: ±full scale spans the signed 16-bit range
        self.rad_per_lsb = np.float32(np.deg2rad(self.full_scale_dps) / 32768.0)
        self.clock = ClockMapper(1.0 / self.rate_hz, window_s=self.clock_window_s, name=self.name)
        self._seq = 0
        self._t_last = math.nan          # host time of the newest sample read (mapped)
        self._t_out = -math.inf          # newest time stamp handed out
        self._gap_pending = False
        self._lost_pending = 0
        self._needs_recovery = False
        self._queue: list[GyroBatch] = []     # batches split off a read at invalid samples
        self._running = False
        self._started = False
        self._next_read = 0.0
        self._wanted = threading.Event()
        self._stats.update(invalid=0, recoveries=0, bad_counts=0, lost_uncertainty=0)

    @property
    def fifo_seconds(self) -> float:
        """How long the FIFO takes to fill at the output data rate."""
        return self.fifo_size / self.packet_size / self.rate_hz

    @property
    def read_interval_s(self) -> float:
        """The FIFO is read this often: an eighth of its fill time, at most 25 ms (a frame that waits for
        samples asks for a read at once, so the interval bounds the CPU, not the latency)."""
        if self._read_interval_s is not None:
            return self._read_interval_s
        return min(READ_INTERVAL_MAX_S, self.fifo_seconds / 8)

    @read_interval_s.setter
    def read_interval_s(self, seconds: float) -> None:
        self._read_interval_s = float(seconds)

    # -- chip hooks ------------------------------------------------------------------------------
    def _identify(self) -> None:
        raise NotImplementedError

    def _configure(self) -> None:
        raise NotImplementedError

    def _fifo_status(self) -> tuple[int, bool]:
        """(bytes in the FIFO, overflow flag)."""
        raise NotImplementedError

    def _flush(self) -> None:
        raise NotImplementedError

    def _read_fifo(self, nbytes: int) -> bytes:
        raise NotImplementedError

    def _decode(self, data: bytes) -> tuple[np.ndarray, np.ndarray, int]:
        """(raw int16 [m, 3] of the valid samples, their sample indices within ``data`` [m], samples in
        ``data`` n ≥ m). Invalid samples still advance the sequence counter (they took a tick) and
        show as lost samples (``gap_before``, ``n_lost``) in front of the next valid one."""
        raise NotImplementedError

    packet_size = 6   # bytes per FIFO record; reads are whole records

    def _power_down(self) -> None:
        pass

    # -- helpers ---------------------------------------------------------------------------------
    @contextmanager
    def _io(self, what: str):
        try:
            yield
        except OSError as e:
            self._stats["io_errors"] += 1
            self._needs_recovery = True
            hint = ("check wiring / I²C address / bus number / SPI mode and power" if not self._running
                    else "check wiring, power and the connector (a replugged chip is re-configured on the "
                    "next poll)")
            raise self.error_type(f"{self.name}: {what} failed: {e.strerror or e} — {hint}") from e

    def _expect(self, reg_name: str, reg: int, value: int, mask: int = 0xFF) -> None:
        got = self.bus.read_u8(reg)
        if (got & mask) != (value & mask):
            raise self.error_type(f"{self.name}: {reg_name} 0x{reg:02X} read back 0x{got:02X}, expected "
                                  f"0x{value & mask:02X} (mask 0x{mask:02X}) — the chip did not accept the "
                                  "configuration: check the bus signal integrity / SPI mode")

    def _check_id(self, reg_name: str, reg: int, expected: int | tuple[int, ...]) -> None:
        got = self.bus.read_u8(reg)
        ok = expected if isinstance(expected, tuple) else (expected,)
        if got not in ok:
            want = " or ".join(f"0x{v:02X}" for v in ok)
            raise self.error_type(f"{self.name}: {reg_name} 0x{reg:02X} read 0x{got:02X}, expected {want} "
                                  "— check wiring / I²C address / bus number / SPI mode, and that this is a "
                                  f"{self.chip}")

    # -- GyroSource ------------------------------------------------------------------------------
    def start(self) -> None:
        with self._io("identification"):
            self._identify()
        with self._io("configuration"):
            self._configure()
            self._flush()
        if self._started:
            self._mark_gap(time.monotonic())     # a restart: what the chip sampled meanwhile is gone
        else:
            self._t_last = time.monotonic()
        self._started = True
        self._needs_recovery = False
        self._running = True
        self._next_read = time.monotonic() + self.read_interval_s

    def stop(self) -> None:
        if not self._running:
            return
        self._running = False
        try:
            self._power_down()
        except OSError:
            pass          # unplugged: nothing left to power down

    def request_read(self) -> None:
        """Read the FIFO now rather than at the next interval: a frame waits for its newest samples.
        The interval bounds the driver's CPU (each read is a few hundred µs of Python); a wake bounds
        the frame's wait, which would otherwise average half the interval."""
        self._wanted.set()

    def wake_on(self, event) -> None:
        """Wait for read requests on `event` (a `threading.Event` or a `multiprocessing.Event` that
        another process sets) instead of this driver's own: setting it is `request_read`."""
        self._wanted = event

    def _wait(self, seconds: float) -> None:
        if self._wanted.wait(max(0.0, seconds)):
            self._wanted.clear()
            self._next_read = min(self._next_read, time.monotonic())

    def poll(self, timeout: float) -> GyroBatch | None:
        if not self._running:
            raise self.error_type(f"{self.name}: poll() before start()")
        deadline = time.monotonic() + max(0.0, timeout)
        if self._queue:
            return self._count_batch(self._queue.pop(0))
        while True:
            now = time.monotonic()
            if self._next_read > now:
                if self._next_read > deadline:
                    self._wait(deadline - now)
                    if self._next_read > time.monotonic():
                        return None
                else:
                    self._wait(self._next_read - now)
            self._next_read = time.monotonic() + self.read_interval_s
            batch = self._read_once()
            if batch is not None:
                return self._count_batch(batch)
            if time.monotonic() >= deadline:
                return None

    # -- the read ---------------------------------------------------------------------------------
    def _recover(self) -> None:
        with self._io("re-configuration after an I/O error"):
            self._identify()
            self._configure()
            self._flush()
        self._stats["recoveries"] += 1
        self._mark_gap(time.monotonic())
        self._needs_recovery = False

    def _mark_gap(self, t_now: float, uncertainty_s: float = 0.0) -> None:
        # every sample between the newest one handed out and now is gone; the count is estimated
        # from host time (± `uncertainty_s`, counted in `lost_uncertainty`), so the counter-to-time
        # fit restarts (keeping its drift), anchored at the flush: the last sample counted as lost was
        # taken by `t_now`, and the next read may come late
        n = max(0, int(round((t_now - self._t_last) * self.rate_hz)))
        self._stats["lost_uncertainty"] += int(math.ceil(uncertainty_s * self.rate_hz))
        self._seq += n
        self._t_last = t_now
        self._gap_pending = True
        self._lost_pending += n
        self.clock.restart(anchor=(self._seq - 1, t_now))

    def _read_once(self) -> GyroBatch | None:
        if self._needs_recovery:
            self._recover()
        with self._io("FIFO status read"):
            count, overflow = self._fifo_status()
        t_count = time.monotonic()
        if overflow or not 0 <= count <= self.fifo_size:
            # an overflow, or a count no FIFO can hold (a bus glitch reads all ones): the content
            # cannot be trusted, so flush it and estimate what was lost from host time
            # the FIFO restarts when the flush reaches the chip, somewhere within this bracket (a
            # reader preempted inside it would otherwise count its preemption as lost samples)
            t0 = time.monotonic()
            with self._io("FIFO flush"):
                self._flush()
            t1 = time.monotonic()
            self._stats["overflows" if overflow else "bad_counts"] += 1
            self._mark_gap(0.5 * (t0 + t1), 0.5 * (t1 - t0))
            return None
        nbytes = count - count % self.packet_size
        if nbytes == 0:
            return None
        with self._io("FIFO burst read"):
            data = self._read_fifo(nbytes)
        raw, offsets, n = self._decode(data)
        if n == 0:
            return None
        seq0 = self._seq
        self._seq += n
        self.clock.observe(self._seq - 1, t_count)
        self._stats["invalid"] += n - len(offsets)
        if len(offsets) == 0:
            self._lost_pending += n                  # a read of invalid samples only: they are missing
            self._gap_pending = True
            return None
        idx = seq0 + offsets
        t = np.asarray(self.clock.to_host(idx), dtype=np.float64)
        if t[0] <= self._t_out:
            # the fit lowered its offset (start-up, after a gap): keep sample times strictly increasing
            t = np.maximum(t, self._t_out + 0.5 / self.rate_hz * np.arange(1, len(t) + 1))
        self._t_out = float(t[-1])
        self._t_last = float(self.clock.to_host(self._seq - 1))
        rate = raw.astype(np.float32) * self.rad_per_lsb
        # invalid samples keep their ticks but are missing: they split the read like lost samples
        bounds = [0, *(np.flatnonzero(np.diff(offsets) != 1) + 1).tolist(), len(offsets)]
        batches = []
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            missing = int(offsets[a] - (offsets[a - 1] + 1 if a else 0))
            lost = missing + (self._lost_pending if a == 0 else 0)
            gap = missing > 0 or (self._gap_pending if a == 0 else False)
            batches.append(GyroBatch(t=t[a:b], rate=rate[a:b], seq=int(idx[a]), gap_before=gap, n_lost=lost))
        trailing = n - 1 - int(offsets[-1])
        self._gap_pending, self._lost_pending = trailing > 0, trailing
        self._queue.extend(batches[1:])
        return batches[0]
