"""Bosch BMI088 gyroscope die (SPI or I²C), read through its FIFO.

Datasheet BST-BMI088-DS001 (rev 1.9), gyroscope register map. The gyro die is a separate
SPI/I²C target from the accelerometer (CHIP_ID 0x0F; I²C 0x68/0x69). ODR and filter are one
BANDWIDTH code (0x02 = 1 kHz / 116 Hz, 0x01 = 2 kHz / 230 Hz); bit 7 of BANDWIDTH always reads 1.
The FIFO holds 100 frames of X, Y, Z int16 little-endian (6 bytes); FIFO_STATUS counts frames
(bits 6:0) and flags an overrun (bit 7). Writing FIFO_CONFIG_1 clears the FIFO and the overrun.
"""

from __future__ import annotations

import time

import numpy as np

from thermod.drivers.gyro_base import FifoGyro, GyroDeviceError

# Gyroscope register map (BST-BMI088-DS001 §10). Values are addresses.
REGISTERS = {
    "GYRO_CHIP_ID": 0x00,      # reads 0x0F
    "FIFO_STATUS": 0x0E,       # bit 7 fifo_overrun, bits 6:0 fifo_frame_counter
    "GYRO_RANGE": 0x0F,        # 0x00 ±2000, 0x01 ±1000, 0x02 ±500, 0x03 ±250, 0x04 ±125 °/s
    "GYRO_BANDWIDTH": 0x10,    # ODR/filter code; bit 7 reads 1
    "GYRO_LPM1": 0x11,         # 0x00 normal, 0x80 suspend, 0x20 deep suspend
    "GYRO_SOFTRESET": 0x14,    # write 0xB6, then wait 30 ms
    "FIFO_CONFIG_0": 0x3D,     # watermark level
    "FIFO_CONFIG_1": 0x3E,     # bits 7:6 mode (0x40 FIFO / stop when full, 0x80 stream), bits 1:0 data select
    "FIFO_DATA": 0x3F,         # FIFO read port
}
CHIP_ID = 0x0F
RANGE = {2000.0: 0x00, 1000.0: 0x01, 500.0: 0x02, 250.0: 0x03, 125.0: 0x04}
BANDWIDTH = {2000.0: 0x01, 1000.0: 0x02, 400.0: 0x03, 200.0: 0x04, 100.0: 0x05}
FIFO_STREAM_XYZ = 0x80
FIFO_FRAMES = 100
SOFTRESET = 0xB6

R = REGISTERS


class BMI088Error(GyroDeviceError):
    """BMI088 gyro identification, configuration or I/O failure."""


class BMI088Gyro(FifoGyro):
    """BMI088 gyroscope source; ``bus`` is a :class:`thermod.drivers.bus.RegisterBus`."""

    chip = "BMI088 gyro"
    error_type = BMI088Error
    fifo_size = FIFO_FRAMES * 6
    full_scales_dps = tuple(RANGE)
    packet_size = 6
    reset_wait_s = 0.03

    def __init__(self, bus, *, full_scale_dps: float = 2000.0, rate_hz: float = 1000.0, **kw):
        if float(rate_hz) not in BANDWIDTH:
            raise BMI088Error(f"{self.chip}: rate_hz={rate_hz!r} is not an ODR of the chip, expected one of "
                              f"{sorted(BANDWIDTH)}")
        super().__init__(bus, full_scale_dps=float(full_scale_dps), rate_hz=float(rate_hz), **kw)

    def _identify(self) -> None:
        self._check_id("GYRO_CHIP_ID", R["GYRO_CHIP_ID"], CHIP_ID)

    def _configure(self) -> None:
        b = self.bus
        b.write(R["GYRO_SOFTRESET"], SOFTRESET)
        time.sleep(self.reset_wait_s)
        b.write(R["GYRO_LPM1"], 0x00)
        b.write(R["GYRO_RANGE"], RANGE[self.full_scale_dps])
        b.write(R["GYRO_BANDWIDTH"], BANDWIDTH[self.rate_hz])
        b.write(R["FIFO_CONFIG_1"], FIFO_STREAM_XYZ)
        self._expect("GYRO_LPM1", R["GYRO_LPM1"], 0x00)
        self._expect("GYRO_RANGE", R["GYRO_RANGE"], RANGE[self.full_scale_dps], 0x07)
        self._expect("GYRO_BANDWIDTH", R["GYRO_BANDWIDTH"], BANDWIDTH[self.rate_hz], 0x0F)
        self._expect("FIFO_CONFIG_1", R["FIFO_CONFIG_1"], FIFO_STREAM_XYZ, 0xC3)

    def _fifo_status(self) -> tuple[int, bool]:
        st = self.bus.read_u8(R["FIFO_STATUS"])
        return (st & 0x7F) * 6, bool(st & 0x80)

    def _flush(self) -> None:
        self.bus.write(R["FIFO_CONFIG_1"], FIFO_STREAM_XYZ)     # clears the FIFO and the overrun flag

    def _read_fifo(self, nbytes: int) -> bytes:
        return self.bus.read(R["FIFO_DATA"], nbytes, fifo=True)

    def _power_down(self) -> None:
        self.bus.write(R["GYRO_LPM1"], 0x80)

    def _decode(self, data: bytes):
        n = len(data) // 6
        raw = np.frombuffer(data, "<i2", count=3 * n).astype(np.int16).reshape(n, 3)
        return raw, np.arange(n), n
