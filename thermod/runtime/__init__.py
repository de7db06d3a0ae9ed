"""The live daemon behind `thermod run`: everything with threads, devices, clocks and sockets.

Configuration (TOML → validated frozen dataclasses), the ring buffers the driver threads write,
device-clock → CLOCK_MONOTONIC mapping, the source registry that turns a configuration `kind` into a
driver (or the simulated payload), the pipeline (scheduler, kernel rendering, deconvolution workers,
in-order output), the supervisor with its health report and signal handling, ZeroMQ publishing and
sd_notify. docs/design.md §6 describes the data flow. It builds on `thermod.physics` and
`thermod.io`, reaches `thermod.drivers` and `thermod.sim` only through the source registry, and
never imports `thermod.calib` or `thermod.cli`. The dependency runs one way: the core
(`thermod.physics`, `thermod.io`, `thermod.calib`) does not import this package, except that
`thermod.calib` reads the configuration module to find the packaged default.
"""
