"""The one I/O seam of the register-chip gyro drivers: a register bus over I²C or SPI.

Drivers talk to a :class:`RegisterBus` (``read(reg, n)``, ``write(reg, value)``) and never to
smbus2/spidev directly. :class:`I2CBus` wraps an ``smbus2.SMBus``-like object and
:class:`SPIBus` a ``spidev.SpiDev``-like object; pass a bus number (or ``(bus, cs)``) to open the
real device, or any object with the same methods (the emulators in ``thermod.sim.emu_registers``)
to test the driver's real code path without hardware.

- I²C: every read is one combined ``i2c_rdwr`` transaction (write register address, repeated
  start, read n bytes): SMBus block reads stop at 32 bytes, a FIFO burst needs hundreds.
  Writes are ``write_byte_data``.
- SPI: ``xfer2([reg | 0x80, 0, …])`` reads, ``xfer2([reg & 0x7F, value])`` writes; spidev moves
  at most 4096 bytes per transfer by default, so longer reads are split.

OSError from the bus propagates unchanged; the driver wraps it in its own exception naming the chip.
"""

from __future__ import annotations

import errno
import re

from thermod.errors import DeviceError


class RegisterBus:
    """Byte-register access to one chip. ``fifo=True`` reads keep the same register address for
    every chunk (a FIFO data port), otherwise chunks continue at the next address."""

    max_read: int = 4096

    def read(self, reg: int, n: int, *, fifo: bool = False) -> bytes:
        out = bytearray()
        while len(out) < n:
            k = min(self.max_read, n - len(out))
            out += self._checked_read(reg if fifo else reg + len(out), k)
        return bytes(out)

    def read_u8(self, reg: int) -> int:
        return self._checked_read(reg, 1)[0]

    def _checked_read(self, reg: int, n: int) -> bytes:
        data = self._read(reg, n)
        if len(data) != n:          # a transfer cut short: an I/O error like any other for the driver
            raise OSError(errno.EIO, f"short read at register 0x{reg:02X}: {len(data)} of {n} bytes")
        return data

    def write(self, reg: int, value: int) -> None:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def _read(self, reg: int, n: int) -> bytes:
        raise NotImplementedError

    def describe(self) -> str:
        raise NotImplementedError


class I2CBus(RegisterBus):
    """A chip at ``address`` on an I²C bus: ``bus`` is a bus number or "/dev/i2c-N", or an SMBus-like object.

    ``max_read`` bounds one ``i2c_rdwr`` read message (Linux i2c-dev refuses more than 8192 bytes).
    """

    def __init__(self, bus: int | str | object = 1, address: int = 0x68, *, max_read: int = 4096):
        from smbus2 import i2c_msg  # pure Python; importing it never touches hardware

        if isinstance(bus, str):
            m = re.fullmatch(r"(?:/dev/i2c-)?(\d+)", bus)
            if not m:
                raise DeviceError(f"I²C bus {bus!r}: expected /dev/i2c-N or a bus number")
            bus = int(m.group(1))
        self._msg = i2c_msg
        self.address = int(address)
        self.max_read = int(max_read)
        self._owns = isinstance(bus, int)
        if self._owns:
            from smbus2 import SMBus
            self.bus_name = f"/dev/i2c-{bus}"
            try:
                self._bus = SMBus(bus)
            except OSError as e:
                raise DeviceError(f"I²C bus {self.bus_name}: cannot open ({e.strerror or e}) — check that "
                                  "the bus exists (raspi-config / dtparam=i2c_arm=on), i2c-dev is loaded "
                                  "and you are in group i2c") from e
        else:
            self._bus = bus
            self.bus_name = getattr(bus, "name", type(bus).__name__)

    def _read(self, reg: int, n: int) -> bytes:
        w = self._msg.write(self.address, [reg & 0xFF])
        r = self._msg.read(self.address, n)
        self._bus.i2c_rdwr(w, r)
        return bytes(r)

    def write(self, reg: int, value: int) -> None:
        self._bus.write_byte_data(self.address, reg & 0xFF, value & 0xFF)

    def close(self) -> None:
        if self._owns:
            self._bus.close()

    def describe(self) -> str:
        return f"I²C {self.bus_name} address 0x{self.address:02X}"


class SPIBus(RegisterBus):
    """A chip on SPI: ``device`` is ``(bus, chip_select)`` or "/dev/spidevB.C", or a SpiDev-like object.

    ``mode`` 3 and ``max_speed_hz`` 8 MHz suit the ICM-42688-P and BMI088; the MPU-6000 accepts
    register writes only up to 1 MHz, so open it with ``max_speed_hz=1_000_000``. The read flag is
    bit 7 of the address byte.
    """

    def __init__(self, device: tuple[int, int] | str | object = (0, 0), *, max_speed_hz: int = 8_000_000,
                 mode: int = 3, max_transfer: int = 4096, read_flag: int = 0x80):
        if isinstance(device, str):
            m = re.fullmatch(r"/dev/spidev(\d+)\.(\d+)", device)
            if not m:
                raise DeviceError(f"SPI device {device!r}: expected /dev/spidevB.C")
            device = (int(m.group(1)), int(m.group(2)))
        self.read_flag = read_flag
        self.max_read = int(max_transfer) - 1           # one byte of every transfer is the address
        self._owns = isinstance(device, tuple)
        if self._owns:
            self.bus_name = f"/dev/spidev{device[0]}.{device[1]}"
            try:
                import spidev
            except ImportError as e:
                raise DeviceError(f"SPI {self.bus_name}: the spidev module is not installed "
                                  "(pip install spidev; Linux only)") from e
            self._dev = spidev.SpiDev()
            try:
                self._dev.open(*device)
            except OSError as e:
                raise DeviceError(f"SPI {self.bus_name}: cannot open ({e.strerror or e}) — check "
                                  "dtparam=spi=on and that you are in group spi") from e
            self._dev.max_speed_hz = int(max_speed_hz)
            self._dev.mode = int(mode)
        else:
            self._dev = device
            self.bus_name = getattr(device, "name", type(device).__name__)

    def _read(self, reg: int, n: int) -> bytes:
        rx = self._dev.xfer2([(reg & 0x7F) | self.read_flag] + [0] * n)
        return bytes(rx[1:])

    def write(self, reg: int, value: int) -> None:
        self._dev.xfer2([reg & 0x7F, value & 0xFF])

    def close(self) -> None:
        if self._owns:
            self._dev.close()

    def describe(self) -> str:
        return f"SPI {self.bus_name}"
