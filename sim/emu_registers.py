"""Register-level emulators of FIFO gyro chips, behind the same bus seam the drivers use.

A chip (:class:`ICM42688Emu`, :class:`MPU6000Emu`, :class:`BMI088GyroEmu`) is a byte register file
with a FIFO that fills at the configured output data rate in real time: on every bus access it
appends the samples whose ODR ticks have passed on its own oscillator (``drift_ppm`` off nominal,
positive = runs fast), taken from ``rate_fn(t) -> [n, 3]`` rad/s in the gyro frame at the host
times ``t`` of the ticks (``clock``, default ``time.monotonic``), plus white noise, quantised at the
configured full scale. A FIFO that is not read overflows as the datasheet says (status bit set,
oldest data lost; the MPU's byte-wise overwrite leaves it misaligned, as the real part does).

Front ends present the chips the way the drivers see real hardware:
:class:`EmuI2C` is an ``smbus2.SMBus`` stand-in offering what :class:`thermod.drivers.bus.I2CBus`
calls (``i2c_rdwr`` with real ``smbus2.i2c_msg`` objects, ``write_byte_data``; unknown addresses
NACK with ``OSError(EREMOTEIO)``) and
:class:`EmuSPI` a ``spidev.SpiDev`` stand-in (``xfer2``, bit 7 of the first byte = read, 4096-byte cap).

Fault injection: ``unplug(seconds)`` (every access raises OSError, then the chip comes back
power-cycled, configuration lost), ``nack(n)`` (the next n transactions fail), ``glitch(n)`` (the
next n reads return all ones, as an undriven data line does, while the chip clocks its data out),
``chip_id=`` (a wrong WHO_AM_I), and simply not reading (overflow).

Cheap at 1 kHz: a poll costs a few tens of µs (one vectorised ``rate_fn`` call per batch).
"""

from __future__ import annotations

import ctypes
import errno
import math
import threading
import time
from collections.abc import Callable

import numpy as np

RateFn = Callable[[np.ndarray], np.ndarray]


class RegisterChip:
    """Base of the emulated chips: registers, the real-time sample clock, the FIFO and faults."""

    name = "chip"
    fifo_reg = 0x00
    fifo_capacity = 1024
    drop_oldest_bytes = False      # MPU: byte-wise overwrite of the oldest data

    def __init__(self, *, rate_fn: RateFn | None = None, clock: Callable[[], float] = time.monotonic,
                 drift_ppm: float = 0.0, noise_rad_s: float = 0.0005, chip_id: int | None = None,
                 seed: int = 0):
        self.rate_fn = rate_fn
        self.clock = clock
        self.drift_ppm = float(drift_ppm)
        self.noise_rad_s = float(noise_rad_s)
        self.chip_id = chip_id
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._unplugged_until = -math.inf
        self._power_cycle_pending = False
        self._nacks = 0
        self._glitches = 0
        self._glitch_reg: int | None = None
        self.invalid_samples = 0       # the next n samples read -32768 (ICM: "not valid yet")
        self.counters = {"generated": 0, "dropped": 0, "overflows": 0, "popped": 0, "flushes": 0}
        self._power_on()

    # -- chip-specific hooks ----------------------------------------------------------------------
    def _defaults(self) -> dict[int, int]:
        raise NotImplementedError

    def odr_hz(self) -> float:
        raise NotImplementedError

    def full_scale_dps(self) -> float:
        raise NotImplementedError

    def fifo_enabled(self) -> bool:
        raise NotImplementedError

    def record_size(self) -> int:
        raise NotImplementedError

    def _pack(self, raw: np.ndarray, t: np.ndarray) -> bytes:
        raise NotImplementedError

    def _on_write(self, reg: int, value: int) -> None:
        pass

    def _read_reg(self, reg: int) -> int:
        return self.regs[reg]

    def _set_overflow(self) -> None:
        raise NotImplementedError

    timeline_regs: tuple[int, ...] = ()   # writes to these restart the sample clock

    # -- state ------------------------------------------------------------------------------------
    def _power_on(self) -> None:
        self.regs = bytearray(128)
        for reg, v in self._defaults().items():
            self.regs[reg] = v
        self.fifo = bytearray()
        self._restart_timeline()

    def _restart_timeline(self) -> None:
        self._epoch = self.clock()
        self._k = 0                   # ODR ticks consumed since the epoch

    def period_s(self) -> float:
        """True sample period of this oscillator (nominal 1/ODR, shortened by +drift)."""
        return 1.0 / (self.odr_hz() * (1.0 + self.drift_ppm * 1e-6))

    def _advance(self) -> None:
        now = self.clock()
        period = self.period_s()
        k_now = int(math.floor((now - self._epoch) / period))
        n = k_now - self._k
        if n <= 0:
            return
        if not self.fifo_enabled():
            self._k = k_now
            return
        size = self.record_size()
        keep = self.fifo_capacity // size + 2            # more would be overwritten anyway
        if n > keep:
            self.counters["dropped"] += n - keep
            self._overflow_now()
            self._k = k_now - keep
            n = keep
        k = np.arange(self._k, k_now)
        t = self._epoch + (k + 1.0) * period
        if self.rate_fn is None:
            rate = np.zeros((n, 3))
        else:
            rate = np.asarray(self.rate_fn(t), np.float64).reshape(n, 3)
        if self.noise_rad_s > 0:
            rate = rate + self._rng.normal(0.0, self.noise_rad_s, rate.shape)
        lsb_per_rad = 32768.0 / math.radians(self.full_scale_dps())
        raw = np.clip(np.rint(rate * lsb_per_rad), -32767, 32767).astype(np.int16)
        if self.invalid_samples > 0:                     # sensor still starting: the chip's invalid marker
            m = min(n, self.invalid_samples)
            raw[:m] = -32768
            self.invalid_samples -= m
        self._k = k_now
        self.counters["generated"] += n
        self._push(self._pack(raw, t), size)

    def _push(self, data: bytes, size: int) -> None:
        self.fifo += data
        excess = len(self.fifo) - self.fifo_capacity
        if excess > 0:
            if not self.drop_oldest_bytes:
                excess = -(-excess // size) * size      # whole records
            self.counters["dropped"] += -(-excess // size)
            del self.fifo[:excess]
            self._overflow_now()

    def _overflow_now(self) -> None:
        self.counters["overflows"] += 1
        self._set_overflow()

    def flush(self) -> None:
        self.fifo.clear()
        self.counters["flushes"] += 1

    def _pop(self, n: int) -> bytes:
        out = bytes(self.fifo[:n])
        del self.fifo[:n]
        self.counters["popped"] += len(out)
        return out + b"\xff" * (n - len(out))           # an empty FIFO reads as all ones

    # -- faults -----------------------------------------------------------------------------------
    def unplug(self, seconds: float, *, power_cycle: bool = True) -> None:
        """Fail every access with OSError for ``seconds``; then come back reset (config lost)."""
        self._unplugged_until = self.clock() + seconds
        self._power_cycle_pending = power_cycle

    def nack(self, n: int = 1) -> None:
        """Fail the next ``n`` bus transactions with OSError (glitches; state is kept)."""
        self._nacks += int(n)

    def glitch(self, n: int = 1, reg: int | None = None) -> None:
        """The next ``n`` reads (of register ``reg`` only, if given) return 0xFF bytes; the chip's FIFO
        still pops what it clocked out."""
        self._glitches += int(n)
        self._glitch_reg = reg

    def check_present(self) -> None:
        """Called by the front ends once per transaction: raises OSError while unplugged."""
        now = self.clock()
        if now < self._unplugged_until:
            raise OSError(errno.EREMOTEIO, f"Remote I/O error ({self.name} not responding)")
        if self._nacks > 0:
            self._nacks -= 1
            raise OSError(errno.EREMOTEIO, f"Remote I/O error ({self.name} NACK)")
        if self._power_cycle_pending:
            self._power_cycle_pending = False
            self._power_on()

    # -- byte access (front ends call these) -------------------------------------------------------
    def read(self, reg: int, n: int) -> bytes:
        with self._lock:
            self._advance()
            if reg == self.fifo_reg:
                out = self._pop(n)
            else:
                out = bytearray()
                for i in range(n):
                    a = (reg + i) & 0x7F
                    out.append(self._pop(1)[0] if a == self.fifo_reg else self._read_reg(a))
            if self._glitches > 0 and self._glitch_reg in (None, reg):
                self._glitches -= 1
                return b"\xff" * n
            return bytes(out)

    def write(self, reg: int, data: bytes) -> None:
        with self._lock:
            self._advance()
            for i, v in enumerate(data):
                a = (reg + i) & 0x7F
                old = self.regs[a]
                self.regs[a] = v & 0xFF
                self._on_write(a, v & 0xFF)
                if a in self.timeline_regs and old != self.regs[a]:
                    self.fifo.clear()                    # new config: samples restart on the new grid
                    self._restart_timeline()


def _int16_be(raw: np.ndarray) -> np.ndarray:
    return raw.astype(">i2").view(np.uint8).reshape(len(raw), -1)


class _InvenSenseChip(RegisterChip):
    """Register conventions the ICM-42688 and the MPU-6000 share: INT_STATUS clears on read and carries
    the FIFO overflow flag; FIFO_COUNT is big-endian in two registers, high then low, and reading the
    high byte latches the low one (a count read in two transfers stays consistent)."""

    int_status_reg: int
    overflow_bit: int
    fifo_count_high_reg: int        # the low byte is the next register

    def _read_reg(self, reg):
        if reg == self.int_status_reg:
            v = self.regs[reg]
            self.regs[reg] = 0
            return v
        if reg == self.fifo_count_high_reg:
            self._count_latch = len(self.fifo)
            return (self._count_latch >> 8) & 0xFF
        if reg == self.fifo_count_high_reg + 1:
            return getattr(self, "_count_latch", len(self.fifo)) & 0xFF
        return self.regs[reg]

    def _set_overflow(self):
        self.regs[self.int_status_reg] |= self.overflow_bit


class ICM42688Emu(_InvenSenseChip):
    """ICM-42688-P (bank 0): WHO_AM_I 0x47, GYRO_CONFIG0, FIFO_CONFIG/1, INT_STATUS FIFO_FULL,
    FIFO_COUNT in bytes (big-endian), packets 2 (8 B, gyro) and 3 (16 B, accel+gyro+timestamp),
    flush by SIGNAL_PATH_RESET bit 1, soft reset by DEVICE_CONFIG bit 0. 2 KB FIFO; stream mode drops
    the oldest packets when full, stop-on-full mode drops new ones."""

    name = "ICM-42688-P"
    fifo_reg = 0x30
    fifo_capacity = 2048
    int_status_reg, overflow_bit = 0x2D, 0x02         # INT_STATUS, FIFO_FULL_INT
    fifo_count_high_reg = 0x2E
    timeline_regs = (0x4E, 0x4F)                      # power and ODR: the sample grid restarts
    FS_DPS = (2000.0, 1000.0, 500.0, 250.0, 125.0, 62.5, 31.25, 15.625)
    ODR_HZ = {1: 32000.0, 2: 16000.0, 3: 8000.0, 4: 4000.0, 5: 2000.0, 6: 1000.0, 7: 200.0, 8: 100.0,
              9: 50.0, 10: 25.0, 11: 12.5, 15: 500.0}

    def _defaults(self):
        return {0x75: 0x47 if self.chip_id is None else self.chip_id, 0x4F: 0x06, 0x4C: 0x30, 0x50: 0x06}

    def odr_hz(self):
        return self.ODR_HZ.get(self.regs[0x4F] & 0x0F, 1000.0)

    def full_scale_dps(self):
        return self.FS_DPS[self.regs[0x4F] >> 5]

    def fifo_enabled(self):
        return (self.regs[0x16] >> 6) != 0 and bool(self.regs[0x5F] & 0x02) and (self.regs[0x4E] & 0x0C) != 0

    def record_size(self):
        return 16 if self.regs[0x5F] & 0x01 else 8

    def _pack(self, raw, t):
        n = len(raw)
        if self.record_size() == 8:
            out = np.empty((n, 8), np.uint8)
            out[:, 0] = 0x20                             # HEADER_GYRO
            out[:, 1:7] = _int16_be(raw)
            out[:, 7] = 0                                # temperature 25 °C
        else:
            out = np.zeros((n, 16), np.uint8)
            out[:, 0] = 0x68                             # accel + gyro + ODR timestamp
            acc = np.zeros((n, 3), np.int16)
            acc[:, 2] = 2048                             # +1 g on z at ±16 g
            out[:, 1:7] = _int16_be(acc)
            out[:, 7:13] = _int16_be(raw)
            ts = (np.rint(t * 1e6).astype(np.int64) & 0xFFFF).astype(">u2")
            out[:, 14:16] = ts.view(np.uint8).reshape(n, 2)
        if self.regs[0x16] >> 6 >= 2 and len(self.fifo) + out.size > self.fifo_capacity:
            room = max(0, (self.fifo_capacity - len(self.fifo)) // out.shape[1])
            if room < n:                                 # stop-on-full: new data is lost
                self.counters["dropped"] += n - room
                self._overflow_now()
                out = out[:room]
        return out.tobytes()

    def _on_write(self, reg, value):
        if reg == 0x11 and value & 0x01:                 # DEVICE_CONFIG soft reset
            self._power_on()
        elif reg == 0x4B:
            if value & 0x02:                             # SIGNAL_PATH_RESET FIFO_FLUSH
                self.flush()
            self.regs[0x4B] = 0                          # bits self-clear


class MPU6000Emu(_InvenSenseChip):
    """MPU-6000/6050: WHO_AM_I 0x68, SMPLRT_DIV/CONFIG (8 kHz with the DLPF off, else 1 kHz, divided),
    GYRO_CONFIG FS_SEL, FIFO_EN (accel, temp, gyro X/Y/Z in register order, big-endian), USER_CTRL
    (FIFO_EN, FIFO_RESET), PWR_MGMT_1 (reset, sleep), INT_STATUS FIFO_OFLOW_INT. The 1 KB FIFO keeps
    the newest 1024 bytes when it overflows, so its content is misaligned afterwards: reset it."""

    name = "MPU-6000"
    fifo_reg = 0x74
    fifo_capacity = 1024
    int_status_reg, overflow_bit = 0x3A, 0x10         # INT_STATUS, FIFO_OFLOW_INT
    fifo_count_high_reg = 0x72
    drop_oldest_bytes = True
    timeline_regs = (0x19, 0x1A, 0x6B)
    FS_DPS = (250.0, 500.0, 1000.0, 2000.0)

    def _defaults(self):
        return {0x75: 0x68 if self.chip_id is None else self.chip_id, 0x6B: 0x40}

    def odr_hz(self):
        base = 8000.0 if self.regs[0x1A] & 0x07 in (0, 7) else 1000.0
        return base / (1 + self.regs[0x19])

    def full_scale_dps(self):
        return self.FS_DPS[(self.regs[0x1B] >> 3) & 0x03]

    def fifo_enabled(self):
        return bool(self.regs[0x6A] & 0x40) and bool(self.regs[0x23] & 0xF8) and not self.regs[0x6B] & 0x40

    def record_size(self):
        en = self.regs[0x23]
        return 6 * bool(en & 0x08) + 2 * bool(en & 0x80) + 2 * sum(bool(en & b) for b in (0x40, 0x20, 0x10))

    def _pack(self, raw, t):
        en, n = self.regs[0x23], len(raw)
        cols = []
        if en & 0x08:
            acc = np.zeros((n, 3), np.int16)
            acc[:, 2] = 2048 * 8 // (1 << ((self.regs[0x1C] >> 3) & 3))   # +1 g
            cols.append(_int16_be(acc))
        if en & 0x80:
            cols.append(_int16_be(np.zeros((n, 1), np.int16)))            # 36.53 °C
        for axis, bit in enumerate((0x40, 0x20, 0x10)):
            if en & bit:
                cols.append(_int16_be(raw[:, axis:axis + 1]))
        return np.concatenate(cols, axis=1).tobytes()

    def _on_write(self, reg, value):
        if reg == 0x6B and value & 0x80:                 # DEVICE_RESET
            self._power_on()
        elif reg == 0x6A:
            if value & 0x04:                             # FIFO_RESET (self-clearing)
                self.flush()
                self.regs[0x6A] &= ~0x04 & 0xFF
            if value & 0x01:                             # SIG_COND_RESET
                self.regs[0x6A] &= ~0x01 & 0xFF


class BMI088GyroEmu(RegisterChip):
    """BMI088 gyro die: CHIP_ID 0x0F, RANGE 0x0F, BANDWIDTH 0x10 (bit 7 reads 1), FIFO_CONFIG_1 0x3E
    (0x40 FIFO/stop-when-full, 0x80 stream), FIFO_STATUS 0x0E (bit 7 overrun, 6:0 frame count),
    FIFO_DATA 0x3F (x, y, z int16 little-endian), 100-frame FIFO, soft reset 0x14 = 0xB6."""

    name = "BMI088-gyro"
    fifo_reg = 0x3F
    fifo_capacity = 600
    timeline_regs = (0x10, 0x11)
    FS_DPS = (2000.0, 1000.0, 500.0, 250.0, 125.0)
    ODR_HZ = (2000.0, 2000.0, 1000.0, 400.0, 200.0, 100.0, 200.0, 100.0)

    def _defaults(self):
        return {0x00: 0x0F if self.chip_id is None else self.chip_id, 0x10: 0x80, 0x3E: 0x00}

    def odr_hz(self):
        return self.ODR_HZ[self.regs[0x10] & 0x07]

    def full_scale_dps(self):
        return self.FS_DPS[min(self.regs[0x0F] & 0x07, 4)]

    def fifo_enabled(self):
        return (self.regs[0x3E] >> 6) in (1, 2) and self.regs[0x11] == 0x00

    def record_size(self):
        return 6

    def _pack(self, raw, t):
        out = raw.astype("<i2").view(np.uint8).reshape(len(raw), 6)
        if self.regs[0x3E] >> 6 == 1 and len(self.fifo) + out.size > self.fifo_capacity:
            room = max(0, (self.fifo_capacity - len(self.fifo)) // 6)
            self.counters["dropped"] += len(raw) - room
            self._overflow_now()
            out = out[:room]
        return out.tobytes()

    def _on_write(self, reg, value):
        if reg == 0x14 and value == 0xB6:                # GYRO_SOFTRESET
            self._power_on()
        elif reg == 0x10:
            self.regs[0x10] = value | 0x80               # bit 7 always reads 1
        elif reg == 0x3E:
            self.flush()                                 # writing FIFO_CONFIG_1 clears the FIFO
            self.regs[0x0E] &= 0x7F

    def _read_reg(self, reg):
        if reg == 0x0E:                                  # overrun stays until FIFO_CONFIG_1 is written
            return (self.regs[0x0E] & 0x80) | min(len(self.fifo) // 6, 0x7F)
        return self.regs[reg]

    def _set_overflow(self):
        self.regs[0x0E] |= 0x80


# -- bus front ends ---------------------------------------------------------------------------------
class EmuI2C:
    """``smbus2.SMBus`` stand-in with chips at addresses: ``EmuI2C({0x68: ICM42688Emu()})``."""

    I2C_M_RD = 0x0001

    def __init__(self, chips: dict[int, RegisterChip] | None = None, name: str = "emulated i2c"):
        self.chips = dict(chips or {})
        self.name = name
        self.transactions = 0

    def _chip(self, addr: int) -> RegisterChip:
        chip = self.chips.get(addr)
        if chip is None:
            raise OSError(errno.EREMOTEIO, f"Remote I/O error (no device at 0x{addr:02X})")
        chip.check_present()
        return chip

    def i2c_rdwr(self, *msgs) -> None:
        self.transactions += 1
        ptr: dict[int, int] = {}
        checked = set()
        for m in msgs:
            chip = self.chips.get(m.addr)
            if m.addr not in checked:
                chip = self._chip(m.addr)
                checked.add(m.addr)
            if m.flags & self.I2C_M_RD:
                data = chip.read(ptr.get(m.addr, 0), m.len)
                ctypes.memmove(m.buf, data, m.len)
                ptr[m.addr] = ptr.get(m.addr, 0) + m.len
            else:
                buf = bytes(m)
                if not buf:
                    continue
                ptr[m.addr] = buf[0]
                if len(buf) > 1:
                    chip.write(buf[0], buf[1:])

    def write_byte_data(self, addr: int, reg: int, value: int) -> None:
        self.transactions += 1
        self._chip(addr).write(reg, bytes([value & 0xFF]))

    def close(self) -> None:
        pass


class EmuSPI:
    """``spidev.SpiDev`` stand-in for one chip select: ``xfer2([reg | 0x80, 0, …])`` reads."""

    def __init__(self, chip: RegisterChip, name: str = "emulated spidev", max_transfer: int = 4096):
        self.chip = chip
        self.name = name
        self.max_transfer = max_transfer
        self.mode = 0
        self.max_speed_hz = 500_000
        self.transactions = 0

    def xfer2(self, data) -> list[int]:
        data = list(data)
        if len(data) > self.max_transfer:
            raise OSError(errno.EMSGSIZE, "Message too long")        # spidev's bufsiz limit
        self.transactions += 1
        self.chip.check_present()
        if self.mode not in (0, 3):
            return [0xFF] * len(data)                    # wrong mode: the chip does not answer
        reg = data[0]
        if reg & 0x80:
            return [0] + list(self.chip.read(reg & 0x7F, len(data) - 1))
        self.chip.write(reg & 0x7F, bytes(data[1:]))
        return [0] * len(data)

    def close(self) -> None:
        pass
