"""Device drivers: gyro sources (register chips over I²C/SPI, serial IMUs, Linux IIO) and cameras.

Every hardware call goes through one injectable seam (``bus=`` for register chips, a port or path
for serial and IIO), so the emulators in ``thermod.sim`` exercise the real driver code.
"""
