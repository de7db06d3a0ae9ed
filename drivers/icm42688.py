"""TDK InvenSense ICM-42688-P gyro over SPI or I²C, read through its FIFO.

Datasheet DS-000347 (rev 1.8). Bank 0 registers only. The FIFO holds 2 KB; in stream mode the chip
records one packet per gyro ODR tick. With only the gyro enabled a packet is 8 bytes
(packet 2: header, gyro X/Y/Z int16 big-endian, temperature int8); with ``fifo_accel=True`` it is
the 16-byte packet 3 (header, accel, gyro, temperature, 16-bit timestamp). The header byte names
the layout (bit 7 = FIFO empty, bit 6 accel, bit 5 gyro, bit 4 20-bit packet), so decoding reads it.

    from thermod.drivers.bus import SPIBus
    gyro = ICM42688(SPIBus((0, 0)), full_scale_dps=500)
    gyro.start(); batch = gyro.poll(0.05)
"""

from __future__ import annotations

import time

import numpy as np

from thermod.drivers.gyro_base import FifoGyro, GyroDeviceError

# Register map, user bank 0 (DS-000347 §14). Values are addresses.
REGISTERS = {
    "DEVICE_CONFIG": 0x11,      # bit 0 SOFT_RESET_CONFIG (wait 1 ms after)
    "FIFO_CONFIG": 0x16,        # bits 7:6 FIFO_MODE: 00 bypass, 01 stream-to-FIFO, 10 stop-on-full
    "INT_STATUS": 0x2D,         # bit 1 FIFO_FULL_INT (clears on read)
    "FIFO_COUNTH": 0x2E,        # FIFO byte count, big-endian with INTF_CONFIG0 defaults
    "FIFO_COUNTL": 0x2F,
    "FIFO_DATA": 0x30,          # FIFO read port (address does not auto-increment)
    "SIGNAL_PATH_RESET": 0x4B,  # bit 1 FIFO_FLUSH
    "INTF_CONFIG0": 0x4C,       # bit 6 COUNT_REC (0 = bytes), bits 5/4 count/data big-endian
    "PWR_MGMT0": 0x4E,          # bits 3:2 GYRO_MODE (11 = low noise), bits 1:0 ACCEL_MODE
    "GYRO_CONFIG0": 0x4F,       # bits 7:5 GYRO_FS_SEL, bits 3:0 GYRO_ODR
    "FIFO_CONFIG1": 0x5F,       # bit 3 TMST_FSYNC_EN, bit 2 TEMP_EN, bit 1 GYRO_EN, bit 0 ACCEL_EN
    "WHO_AM_I": 0x75,           # reads 0x47
    "REG_BANK_SEL": 0x76,       # bits 2:0 bank
}
WHO_AM_I_VALUE = 0x47
GYRO_FS_SEL = {2000.0: 0, 1000.0: 1, 500.0: 2, 250.0: 3, 125.0: 4, 62.5: 5, 31.25: 6, 15.625: 7}
GYRO_ODR = {32000.0: 1, 16000.0: 2, 8000.0: 3, 4000.0: 4, 2000.0: 5, 1000.0: 6, 200.0: 7, 100.0: 8,
            50.0: 9, 25.0: 10, 12.5: 11, 500.0: 15}
FIFO_SIZE = 2048
INT_FIFO_FULL = 0x02
FIFO_MODE_STREAM = 0x40
FIFO_FLUSH = 0x02
INTF_CONFIG0_BIG_ENDIAN = 0x30
PWR_GYRO_LOW_NOISE = 0x0C
HDR_EMPTY, HDR_ACCEL, HDR_GYRO, HDR_20 = 0x80, 0x40, 0x20, 0x10
INVALID = -32768               # the chip's marker for a sample not yet valid (sensor starting up)

R = REGISTERS


class ICM42688Error(GyroDeviceError):
    """ICM-42688-P identification, configuration or I/O failure."""


def packet_size(header: int) -> int:
    """Bytes in the FIFO packet whose header byte is ``header`` (0 for an empty/invalid header)."""
    if header & HDR_EMPTY or not header & (HDR_ACCEL | HDR_GYRO):
        return 0
    if header & HDR_20:
        return 20
    return 16 if (header & (HDR_ACCEL | HDR_GYRO)) == (HDR_ACCEL | HDR_GYRO) else 8


class ICM42688(FifoGyro):
    """ICM-42688-P gyro source. ``bus`` is a :class:`thermod.drivers.bus.RegisterBus` (SPI or I²C)."""

    chip = "ICM-42688-P"
    error_type = ICM42688Error
    fifo_size = FIFO_SIZE
    full_scales_dps = tuple(GYRO_FS_SEL)

    def __init__(self, bus, *, full_scale_dps: float = 2000.0, rate_hz: float = 1000.0,
                 fifo_accel: bool = False, **kw):
        if float(rate_hz) not in GYRO_ODR:
            raise ICM42688Error(f"{self.chip}: rate_hz={rate_hz!r} is not an ODR of the chip, expected one "
                                f"of {sorted(GYRO_ODR)}")
        super().__init__(bus, full_scale_dps=float(full_scale_dps), rate_hz=rate_hz, **kw)
        self.fifo_accel = bool(fifo_accel)
        self.packet_size = 16 if fifo_accel else 8
        self._gyro_at = 7 if fifo_accel else 1      # gyro X high byte within the packet

    def _identify(self) -> None:
        self.bus.write(R["REG_BANK_SEL"], 0)
        self._check_id("WHO_AM_I", R["WHO_AM_I"], WHO_AM_I_VALUE)

    def _configure(self) -> None:
        b = self.bus
        b.write(R["DEVICE_CONFIG"], 0x01)               # soft reset: known state after a replug
        time.sleep(0.001)
        b.write(R["REG_BANK_SEL"], 0)
        b.write(R["INTF_CONFIG0"], INTF_CONFIG0_BIG_ENDIAN)
        gyro_config0 = (GYRO_FS_SEL[self.full_scale_dps] << 5) | GYRO_ODR[self.rate_hz]
        b.write(R["GYRO_CONFIG0"], gyro_config0)
        fifo_config1 = 0x03 if self.fifo_accel else 0x02
        b.write(R["FIFO_CONFIG1"], fifo_config1)
        b.write(R["FIFO_CONFIG"], FIFO_MODE_STREAM)
        b.write(R["PWR_MGMT0"], PWR_GYRO_LOW_NOISE | (0x03 if self.fifo_accel else 0))
        time.sleep(0.0003)                              # no register writes for 200 µs after PWR_MGMT0
        self._expect("GYRO_CONFIG0", R["GYRO_CONFIG0"], gyro_config0)
        self._expect("INTF_CONFIG0", R["INTF_CONFIG0"], INTF_CONFIG0_BIG_ENDIAN, 0x70)
        self._expect("FIFO_CONFIG1", R["FIFO_CONFIG1"], fifo_config1, 0x1F)
        self._expect("FIFO_CONFIG", R["FIFO_CONFIG"], FIFO_MODE_STREAM, 0xC0)
        self._expect("PWR_MGMT0", R["PWR_MGMT0"], PWR_GYRO_LOW_NOISE, 0x0C)

    def _fifo_status(self) -> tuple[int, bool]:
        # INT_STATUS, FIFO_COUNTH, FIFO_COUNTL are adjacent: one transaction
        st, hi, lo = self.bus.read(R["INT_STATUS"], 3)
        return (hi << 8) | lo, bool(st & INT_FIFO_FULL)

    def _flush(self) -> None:
        self.bus.write(R["SIGNAL_PATH_RESET"], FIFO_FLUSH)
        self.bus.read_u8(R["INT_STATUS"])    # a FIFO_FULL latched while the full FIFO was being flushed

    def _read_fifo(self, nbytes: int) -> bytes:
        return self.bus.read(R["FIFO_DATA"], nbytes, fifo=True)

    def _power_down(self) -> None:
        self.bus.write(R["PWR_MGMT0"], 0x00)

    def _decode(self, data: bytes):
        buf = np.frombuffer(data, np.uint8)
        size = self.packet_size
        n = len(buf) // size
        pk = buf[: n * size].reshape(n, size)
        if not np.all(pk[:, 0] == pk[0, 0]) or packet_size(int(pk[0, 0])) != size:
            return self._decode_mixed(buf)
        g = self._gyro_at
        raw = pk[:, g:g + 6].copy().view(">i2").astype(np.int16)
        valid = np.flatnonzero(raw[:, 0] != INVALID)
        return raw[valid], valid, n

    def _decode_mixed(self, buf: np.ndarray):
        # unexpected layouts (a reconfiguration in flight, an empty marker, a bus glitch): walk the
        # headers; what follows an unreadable header was read out of the FIFO all the same, so its
        # packets keep their ticks and count as invalid
        rows, offsets, i, k = [], [], 0, 0
        while i < len(buf):
            size = packet_size(int(buf[i]))
            if size == 0 or i + size > len(buf):
                break
            if buf[i] & HDR_GYRO:
                g = i + (7 if buf[i] & HDR_ACCEL else 1)
                v = buf[g:g + 6].copy().view(">i2").astype(np.int16)
                if v[0] != INVALID:
                    rows.append(v)
                    offsets.append(k)
                k += 1
            i += size
        k += (len(buf) - i) // self.packet_size
        raw = np.array(rows, np.int16).reshape(-1, 3)
        return raw, np.array(offsets, np.int64), k
