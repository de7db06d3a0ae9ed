"""TDK InvenSense MPU-6000 (SPI or I²C) / MPU-6050 (I²C) gyro, read through its FIFO.

Register map rev 4.2 (RM-MPU-6000A-00). The sample rate is the gyro output rate (8 kHz with the
digital low-pass filter off, 1 kHz with it on) divided by 1 + SMPLRT_DIV. With only the gyro
enabled in FIFO_EN, each FIFO record is 6 bytes: X, Y, Z int16 big-endian. The FIFO holds 1024
bytes and on overflow keeps writing over the oldest *bytes* (1024 is not a multiple of 6), so
after an overflow its content is misaligned and the only safe action is a FIFO reset.

    from thermod.drivers.bus import I2CBus
    gyro = MPU6000(I2CBus(1, 0x68), full_scale_dps=1000)
"""

from __future__ import annotations

import time

import numpy as np

from thermod.drivers.bus import SPIBus
from thermod.drivers.gyro_base import FifoGyro, GyroDeviceError

# Register map (RM-MPU-6000A-00 rev 4.2). Values are addresses.
REGISTERS = {
    "SMPLRT_DIV": 0x19,     # sample rate = gyro output rate / (1 + SMPLRT_DIV)
    "CONFIG": 0x1A,         # bits 2:0 DLPF_CFG: 0 or 7 → 8 kHz gyro output, 1..6 → 1 kHz
    "GYRO_CONFIG": 0x1B,    # bits 4:3 FS_SEL: 0 ±250, 1 ±500, 2 ±1000, 3 ±2000 °/s
    "FIFO_EN": 0x23,        # bit 7 TEMP, 6 XG, 5 YG, 4 ZG, 3 ACCEL
    "INT_ENABLE": 0x38,     # bit 4 FIFO_OFLOW_EN
    "INT_STATUS": 0x3A,     # bit 4 FIFO_OFLOW_INT (clears on read)
    "USER_CTRL": 0x6A,      # bit 6 FIFO_EN, bit 4 I2C_IF_DIS (SPI only), bit 2 FIFO_RESET
    "PWR_MGMT_1": 0x6B,     # bit 7 DEVICE_RESET, bit 6 SLEEP, bits 2:0 CLKSEL (1 = PLL, X gyro)
    "FIFO_COUNTH": 0x72,    # FIFO byte count, big-endian
    "FIFO_COUNTL": 0x73,
    "FIFO_R_W": 0x74,       # FIFO read port
    "WHO_AM_I": 0x75,       # reads 0x68 (bits 6:1 = 0x34)
}
WHO_AM_I_VALUE = 0x68
FS_SEL = {250.0: 0, 500.0: 1, 1000.0: 2, 2000.0: 3}
FIFO_SIZE = 1024
FIFO_GYRO_XYZ = 0x70
USER_FIFO_EN, USER_I2C_IF_DIS, USER_FIFO_RESET = 0x40, 0x10, 0x04
INT_FIFO_OFLOW = 0x10
PWR_RESET, PWR_SLEEP, PWR_CLK_PLL_X = 0x80, 0x40, 0x01

R = REGISTERS


class MPU6000Error(GyroDeviceError):
    """MPU-6000/6050 identification, configuration or I/O failure."""


class MPU6000(FifoGyro):
    """MPU-6000/6050 gyro source; ``rate_hz`` must divide 1000 (DLPF 188 Hz) or be 8000 (DLPF off)."""

    chip = "MPU-6000/6050"
    error_type = MPU6000Error
    fifo_size = FIFO_SIZE
    full_scales_dps = tuple(FS_SEL)
    packet_size = 6
    reset_wait_s = 0.1            # datasheet: 100 ms after DEVICE_RESET

    def __init__(self, bus, *, full_scale_dps: float = 2000.0, rate_hz: float = 1000.0, **kw):
        rate_hz = float(rate_hz)
        if rate_hz == 8000.0:
            self._dlpf, self._div = 0, 0
        elif 0 < rate_hz <= 1000.0 and (1000.0 / rate_hz).is_integer() and 1000.0 / rate_hz <= 256:
            self._dlpf, self._div = 1, int(1000.0 / rate_hz) - 1
        else:
            raise MPU6000Error(f"{self.chip}: rate_hz={rate_hz!r} is not reachable: expected 8000 or 1000/N "
                               "(N = 1..256)")
        super().__init__(bus, full_scale_dps=float(full_scale_dps), rate_hz=rate_hz, **kw)
        self._spi = isinstance(bus, SPIBus)

    def _identify(self) -> None:
        self._check_id("WHO_AM_I", R["WHO_AM_I"], WHO_AM_I_VALUE)

    def _user_ctrl(self) -> int:
        return USER_FIFO_EN | (USER_I2C_IF_DIS if self._spi else 0)

    def _configure(self) -> None:
        b = self.bus
        b.write(R["PWR_MGMT_1"], PWR_RESET)
        time.sleep(self.reset_wait_s)
        b.write(R["PWR_MGMT_1"], PWR_CLK_PLL_X)         # wake, gyro-referenced PLL (stabler than 8 MHz RC)
        if self._spi:
            b.write(R["USER_CTRL"], USER_I2C_IF_DIS)
        b.write(R["CONFIG"], self._dlpf)
        b.write(R["SMPLRT_DIV"], self._div)
        gyro_config = FS_SEL[self.full_scale_dps] << 3
        b.write(R["GYRO_CONFIG"], gyro_config)
        b.write(R["FIFO_EN"], FIFO_GYRO_XYZ)
        b.write(R["INT_ENABLE"], INT_FIFO_OFLOW)
        b.write(R["USER_CTRL"], self._user_ctrl() | USER_FIFO_RESET)
        self._expect("PWR_MGMT_1", R["PWR_MGMT_1"], PWR_CLK_PLL_X, 0xC7)
        self._expect("CONFIG", R["CONFIG"], self._dlpf, 0x07)
        self._expect("SMPLRT_DIV", R["SMPLRT_DIV"], self._div)
        self._expect("GYRO_CONFIG", R["GYRO_CONFIG"], gyro_config, 0x18)
        self._expect("FIFO_EN", R["FIFO_EN"], FIFO_GYRO_XYZ)
        self._expect("USER_CTRL", R["USER_CTRL"], self._user_ctrl(), 0x50)

    def _fifo_status(self) -> tuple[int, bool]:
        st = self.bus.read_u8(R["INT_STATUS"])
        hi, lo = self.bus.read(R["FIFO_COUNTH"], 2)
        return (hi << 8) | lo, bool(st & INT_FIFO_OFLOW)

    def _flush(self) -> None:
        self.bus.write(R["USER_CTRL"], self._user_ctrl() | USER_FIFO_RESET)
        self.bus.read_u8(R["INT_STATUS"])    # an overflow latched while the full FIFO was being reset

    def _read_fifo(self, nbytes: int) -> bytes:
        return self.bus.read(R["FIFO_R_W"], nbytes, fifo=True)

    def _power_down(self) -> None:
        self.bus.write(R["PWR_MGMT_1"], PWR_SLEEP)

    def _decode(self, data: bytes):
        n = len(data) // 6
        raw = np.frombuffer(data, ">i2", count=3 * n).astype(np.int16).reshape(n, 3)
        return raw, np.arange(n), n
