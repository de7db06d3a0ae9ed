"""The live daemon behind `thermod run`: everything with threads, devices, clocks and sockets.

Configuration (TOML → validated frozen dataclasses), the ring buffers the driver threads write, the
source registry that turns a configuration `kind` into a driver (or the simulated payload), the
pipeline (scheduler, deconvolution workers, in-order output), the governor, the supervisor with its
health report and signal handling, ZeroMQ publishing, RTSP and sd_notify. docs/design.md §6 describes
the data flow.

It builds on the layers below it (`thermod.physics`, `thermod.io`, `thermod.calib`, `thermod.restore`,
`thermod.drivers`, `thermod.sim`) and is used by `thermod.client`, `thermod.batch` and `thermod.cli`;
the layers contract in pyproject.toml (`make lint`) keeps it that way.
"""
