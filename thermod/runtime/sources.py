"""The driver registry: each source ``kind`` of ``[sources.gyro]`` / ``[sources.camera]`` with its
option schema (`Key`s, read by `thermod.runtime.config`) and its constructor (called by the daemon).

This is the one place that lists the kinds and the one place the daemon imports drivers — and the
simulated payload (`thermod.sim`), which is imported lazily by `simulated_payload` and by the ``sim``
constructors, never by the daemon itself.
"""

from __future__ import annotations

import functools
import ipaddress
import math
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from thermod.errors import ConfigError, ThermodError
from thermod.io.toml_tables import Key
from thermod.paths import input_problem

if TYPE_CHECKING:
    from thermod.io.clock import ClockMapper
    from thermod.physics.calibration import Calibration
    from thermod.runtime.config import Config


@runtime_checkable
class Source(Protocol):
    """What the daemon needs of a gyro or camera source (drivers/gyro_base.py, drivers/camera_base.py).

    ``clock`` is the source's device-clock → host mapping, or None when it has none (replay, not
    started yet); its fit quality goes into the health message.
    """

    name: str

    @property
    def clock(self) -> ClockMapper | None: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def poll(self, timeout: float) -> Any: ...

    def stats(self) -> dict: ...


@dataclass(frozen=True)
class Driver:
    """One source kind. `device` says what the table's device key is: ``"device file"`` (key
    ``device``, must exist), ``"recording"`` (key ``path``), ``"id"`` (key ``device``, any string) or
    None (no device). `build(cfg, payload)` constructs the source without opening it."""

    kind: str
    device: str | None
    options: Mapping[str, Key] = field(default_factory=dict)
    build: Callable[[Config, Any], Source] | None = None


# ------------------------------------------------------------------------------------ constructors
def _bus_numbers(cfg: Config, spi: bool) -> tuple[int, ...]:
    """(bus, chip select) of /dev/spidevB.C, or (bus,) of /dev/i2c-N."""
    dev = os.path.realpath(cfg.gyro.device)       # a udev symlink (/dev/thermod/...) names the node
    base = os.path.basename(dev)
    try:
        if spi:
            b, c = base.removeprefix("spidev").split(".")
            return int(b), int(c)
        return (int(base.removeprefix("i2c-")),)
    except ValueError:
        want = "/dev/spidevB.C" if spi else "/dev/i2c-N"
        raise ConfigError(f"{cfg.path}: sources.gyro.device: expected {want} (or a link to it), got "
                          f"{cfg.gyro.device!r}") from None


def _register_bus(cfg: Config, spi: bool):
    from thermod.drivers.bus import I2CBus, SPIBus

    o = cfg.gyro.options
    if spi:
        return SPIBus(_bus_numbers(cfg, True), max_speed_hz=o["speed_hz"])
    return I2CBus(_bus_numbers(cfg, False)[0], o["address"])


def _chip_kw(cfg: Config) -> dict:
    o = cfg.gyro.options
    return dict(full_scale_dps=float(o["full_scale_dps"]), rate_hz=float(o["odr_hz"]))


def _icm42688(spi: bool):
    def build(cfg, payload):
        from thermod.drivers.icm42688 import ICM42688
        return ICM42688(_register_bus(cfg, spi), **_chip_kw(cfg))
    return build


def _mpu6000(cfg, payload):
    from thermod.drivers.mpu6000 import MPU6000
    return MPU6000(_register_bus(cfg, True), **_chip_kw(cfg))


def _bmi088(cfg, payload):
    from thermod.drivers.bmi088 import BMI088Gyro
    return BMI088Gyro(_register_bus(cfg, cfg.gyro.options["bus"] == "spi"), **_chip_kw(cfg))


def _iio(cfg, payload):
    from thermod.drivers.iio import IIOGyro
    o = cfg.gyro.options
    return IIOGyro(cfg.gyro.device, rate_hz=o["rate_hz"] or cfg.calibration.rate_hz,
                   buffer_length=o["buffer_length"])


def _serial(cfg, payload):
    from thermod.drivers.serial_imu import SerialIMU
    o = cfg.gyro.options
    return SerialIMU(cfg.gyro.device, baud=o["baud"], rate_hz=float(cfg.calibration.rate_hz),
                     low_latency=o["low_latency"])


def _replay_gyro(cfg, payload):
    from thermod.drivers import replay
    return replay.ReplayGyro(cfg.gyro.device, loop=cfg.gyro.options["loop"], speed=cfg.gyro.options["speed"])


def _replay_camera(cfg, payload):
    from thermod.drivers import replay
    return replay.ReplayCamera(cfg.camera.device, loop=cfg.camera.options["loop"],
                               speed=cfg.camera.options["speed"])


def _aravis(cfg, payload):
    from thermod.drivers.aravis_camera import AravisCamera
    c, o = cfg.camera, cfg.camera.options
    try:
        ipaddress.ip_address(c.device)
        where = {"address": c.device}
    except ValueError:
        where = {"device_id": c.device}
    return AravisCamera(**where, width=cfg.calibration.width, height=cfg.calibration.height,
                        frame_rate_hz=o["frame_rate_hz"] or None, pixel_formats=(o["pixel_format"],),
                        packet_size=o["packet_size"] or None, stall_timeout_s=o["stream_timeout_s"],
                        ffc_feature=o["ffc_feature"] or None)


def _v4l2(cfg, payload):
    from thermod.drivers.v4l2_camera import V4L2Camera
    o = cfg.camera.options
    return V4L2Camera(cfg.camera.device, width=o["width"], height=o["height"], fourcc=o["fourcc"],
                      frame_rate_hz=o["frame_rate_hz"] or None,
                      telemetry_rows=(o["telemetry_top"], o["telemetry_bottom"]),
                      telemetry=None if o["telemetry"] == "none" else o["telemetry"],
                      timestamp_clock=o["timestamp_clock"], timestamp_offset_s=o["timestamp_offset_s"])


def _video_gyro(cfg, payload):
    from thermod.drivers.video_gyro import VideoGyro
    o = cfg.gyro.options
    return VideoGyro(cfg.calibration, rate_hz=o["rate_hz"], work_width=o["work_width"])


def _sim_gyro(cfg, payload):
    return payload.gyro_source()


def _sim_camera(cfg, payload):
    return payload.camera_source()


# ------------------------------------------------------------------------------------ the registry
_ODR = (1000, 2000, 4000, 8000)
_FS = (125, 250, 500, 1000, 2000)
_REPLAY = {"loop": Key(bool, True), "speed": Key(float, 1.0, 0.01, float("inf"))}  # inf = flat out
CALIBRATION_FROM = ("recording", "config")
_REPLAY_CAMERA = {**_REPLAY, "calibration": Key(
    str, "recording", choices=CALIBRATION_FROM,
    doc="the calibration a replayed camera runs with: its recording's own, or the config's [calibration]")}


# a FIFO or stream gyro read in a process of its own (`thermod.runtime.gyro_process`): its deadline never
# waits on the daemon's GIL
_OWN_PROCESS = {"own_process": Key(bool, True, doc="read it in a process of its own (a GIL of its own)")}


def _table(*drivers: Driver) -> Mapping[str, Driver]:
    return MappingProxyType({d.kind: d for d in drivers})


GYROS: Mapping[str, Driver] = _table(
    Driver("sim", None, {**_OWN_PROCESS}, _sim_gyro),
    Driver("replay", "recording", _REPLAY, _replay_gyro),
    Driver("icm42688_spi", "device file", {"speed_hz": Key(int, 10_000_000, 100_000, 24_000_000),
                                           "odr_hz": Key(int, 1000, choices=_ODR),
                                           "full_scale_dps": Key(int, 2000, choices=_FS), **_OWN_PROCESS},
           _icm42688(True)),
    Driver("icm42688_i2c", "device file", {"address": Key(int, 0x68, choices=(0x68, 0x69)),
                                           "odr_hz": Key(int, 1000, choices=_ODR),
                                           "full_scale_dps": Key(int, 2000, choices=_FS), **_OWN_PROCESS},
           _icm42688(False)),
    Driver("mpu6000", "device file", {"speed_hz": Key(int, 1_000_000, 100_000, 20_000_000),
                                      "odr_hz": Key(int, 1000, choices=(1000, 8000)),
                                      "full_scale_dps": Key(int, 2000, choices=(250, 500, 1000, 2000)),
                                      **_OWN_PROCESS}, _mpu6000),
    Driver("bmi088", "device file", {"bus": Key(str, "spi", choices=("spi", "i2c")),
                                     "address": Key(int, 0x68, choices=(0x68, 0x69)),
                                     "speed_hz": Key(int, 10_000_000, 100_000, 10_000_000),
                                     "odr_hz": Key(int, 1000, choices=(1000, 2000)),
                                     "full_scale_dps": Key(int, 2000, choices=_FS), **_OWN_PROCESS}, _bmi088),
    Driver("iio", "device file", {"buffer_length": Key(int, 256, 2, 65536),
                                  "rate_hz": Key(float, 1000.0, 1.0, 32000.0), **_OWN_PROCESS}, _iio),
    Driver("serial", "device file", {"baud": Key(int, 921600, 1200, 12_000_000),
                                     "low_latency": Key(bool, True), **_OWN_PROCESS}, _serial),
    # no gyro: the rotation measured from the camera's own frames (drivers/video_gyro.py)
    Driver("video", None, {"rate_hz": Key(float, 1000.0, 100.0, 4000.0, doc="samples per second it sends"),
                           "work_width": Key(int, 160, 64, 640, doc="width of the images it registers (px)")},
           _video_gyro),
)

CAMERAS: Mapping[str, Driver] = _table(
    Driver("sim", None, {}, _sim_camera),
    Driver("replay", "recording", _REPLAY_CAMERA, _replay_camera),
    # Aravis opens by device id or IP address: not a file.
    Driver("aravis", "id", {"pixel_format": Key(str, "Mono16", choices=("Mono16", "Mono14", "Mono12")),
                            "packet_size": Key(int, 0, 0, 9000),
                            "frame_rate_hz": Key(float, 0.0, 0.0, 1000.0),
                            "stream_timeout_s": Key(float, 1.0, 0.01, 60.0),
                            # GenICam feature reporting a flat-field correction; "" = a known name
                            "ffc_feature": Key(str, "")}, _aravis),
    Driver("v4l2", "device file", {"width": Key(int, 640, 1, 8192), "height": Key(int, 480, 1, 8192),
                                   "fourcc": Key(str, "Y16 "),
                                   "frame_rate_hz": Key(float, 0.0, 0.0, 1000.0),
                                   # rows the camera adds to each image (FLIR Boson telemetry: 2), stripped
                                   "telemetry_top": Key(int, 0, 0, 64),
                                   "telemetry_bottom": Key(int, 0, 0, 64),
                                   # what the telemetry rows hold: Boson (FFC state read), or none
                                   "telemetry": Key(str, "boson", choices=("boson", "none")),
                                   "timestamp_clock": Key(str, "auto",
                                                             choices=("auto", "monotonic", "device")),
                                   "timestamp_offset_s": Key(float, 0.0, -1.0, 1.0)}, _v4l2),
)

REGISTRY: Mapping[str, Mapping[str, Driver]] = MappingProxyType({"gyro": GYROS, "camera": CAMERAS})


# ------------------------------------------------------------------------------------ entry points
def simulated_payload(cfg: Config):
    """The simulated payload both ``sim`` sources play from (None unless a source is ``sim``)."""
    if not cfg.uses_sim:
        return None
    from thermod.sim.payload import SimPayload
    return SimPayload(cfg.sim, cfg.calibration)


# The payload's gyro is an emulated ICM-42688-P at ±2000 °/s (`thermod.sim.payload.emulated_icm42688`): a
# faster motion would clip there, and the loop's pre-render takes time in proportion to the rate.
SIM_GYRO_FULL_SCALE_DPS = 2000.0


def sim_problems(sim) -> Iterator[tuple[str, str]]:
    """(key, what was expected) for each spec of a ``[sim]`` table (`SimConfig`) the payload could not
    play: an unknown scene or one whose image is unreadable, a motion it cannot parse, one that does not
    loop, is not finite or turns faster than its gyro measures."""
    import numpy as np

    from thermod.sim import playback, scenes

    try:
        name = sim.scene.partition(":")[0]
        if name == "real":
            scenes.real_frame(sim.scene)            # None: no real frames, the texture stands in
        elif not sim.scene.strip():
            raise ThermodError("got ''")
        elif name not in ("bars", "points", "texture"):
            if (problem := input_problem(sim.scene)) is not None:
                raise ThermodError(f"{sim.scene!r} {problem}")
            scenes.read_image(sim.scene)
    except ThermodError as e:
        yield "scene", f"expected bars, points, texture, real[:N] or an image file: {_unprefixed(e)}"
    try:
        with np.errstate(all="ignore"):             # an overflow is an infinite rate, refused below
            motion = playback.loop_motion(sim.motion, sim.loop_s, sim.seed)
            t = np.linspace(0.0, sim.loop_s, min(200_001, int(sim.loop_s * 1000) + 1))
            peak = float(np.degrees(np.abs(motion.omega(t)).max()))
    except (ThermodError, ValueError, ArithmeticError) as e:
        yield "motion", f"expected a looping motion spec (sway, static, shake, vibration, multirotor): " \
                        f"{_unprefixed(e)}"
        return
    if not peak <= SIM_GYRO_FULL_SCALE_DPS:
        got = f"peak {peak:.4g} °/s" if math.isfinite(peak) else "a rate that is not finite"
        yield "motion", (f"expected a motion within the simulated gyro's ±{SIM_GYRO_FULL_SCALE_DPS:g} °/s, "
                         f"got {sim.motion!r} ({got})")


def _unprefixed(e: Exception) -> str:
    """A simulator message without the command-line option it names (``--motion``, ``--scene``)."""
    text = str(e) or type(e).__name__
    return text.removeprefix("--motion ").removeprefix("--motion: ").removeprefix("--scene ")


def calibration_in_force(cfg: Config, camera: Source) -> tuple[Calibration, str]:
    """The calibration the daemon starts with and where it comes from: a replayed recording's own
    (``[sources.camera] kind = "replay"``, ``calibration = "recording"``, the default: the recording was
    made, or fitted, with it), else the configuration's ``[calibration]`` (``"config"``)."""
    if cfg.camera.kind == "replay" and cfg.camera.options.get("calibration") == "recording":
        recorded = getattr(camera, "calibration", None)
        if recorded is not None:
            return recorded, f"recording {cfg.camera.device}"
    return cfg.calibration, "config"


def build(role: str, cfg: Config, payload=None) -> Source:
    """The configured ``role`` ("gyro" or "camera") source, constructed but not started."""
    src = getattr(cfg, role)
    try:
        driver = REGISTRY[role][src.kind]
    except KeyError:
        raise ConfigError(f"{cfg.path}: sources.{role}.kind: no driver for {src.kind!r}") from None
    if src.kind == "sim" and payload is None:
        raise ConfigError(f"{cfg.path}: sources.{role}.kind: 'sim' needs the simulated payload")
    try:
        return driver.build(cfg, payload)
    except ImportError as e:
        raise ConfigError(f"{cfg.path}: sources.{role}.kind: the {src.kind!r} driver is not available "
                          f"({e})") from None


def build_gyro(cfg: Config, payload=None) -> Source:
    return build("gyro", cfg, payload)


def gyro_builder(cfg: Config, payload=None):
    """A picklable constructor of the configured gyro, for the gyro process: the simulated payload's
    emulated chip (after `SimPayload.start`), else `build_gyro` on the configuration."""
    if cfg.gyro.kind == "sim":
        return payload.gyro_builder()
    return functools.partial(build_gyro, cfg)


def build_camera(cfg: Config, payload=None) -> Source:
    return build("camera", cfg, payload)
