"""Daemon configuration: TOML (tomllib) → validated, frozen dataclasses.

Every problem (unknown key, wrong type, out-of-range value, missing device or key file) raises
one `ConfigError` whose message names the file, the dotted key (e.g. ``deblur.lambda``) and what
was expected. `load(None)` reads the packaged default, ``thermod.configs/sim.toml`` (the simulated
payload). `overrides` ({dotted key: value}) are applied on top of the file before validation, so
command-line settings get the same checks as the file.

Sections: ``[sources.gyro]``, ``[sources.camera]``, ``[sim]`` (only with a simulated source),
``[calibration]`` (→ `thermod.physics.calibration.Calibration`), ``[deblur]``, ``[publish]``,
``[pipeline]``, ``[logging]``, ``[radiometry]`` (→ `thermod.physics.radiometry`; model "none" by default),
``[rtsp]`` (the H.264 live view, `thermod.runtime.rtsp`), ``[monitor]`` (the live calibration monitor,
`thermod.runtime.monitor`).
"""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

from thermod.errors import ConfigError
from thermod.io.calibration_file import calibration_from_table
from thermod.io.toml_tables import Section, read_toml
from thermod.physics import radiometry as radiometrymod
from thermod.physics.calibration import Calibration
from thermod.restore.settings import DeblurConfig
from thermod.runtime import sources


# ------------------------------------------------------------------------------ dataclasses
@dataclass(frozen=True)
class SourceConfig:
    """One device. `device` is the device node / sysfs dir / port / recording path / camera id the
    driver opens (None for `sim`); `options` are the kind's remaining parameters (read-only)."""

    kind: str
    device: str | None = None
    options: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    poll_timeout_s: float = 0.005
    realtime_priority: int = 0       # SCHED_FIFO priority of the driver thread (0 = normal)
    retry_max_s: float = 2.0         # reconnect back-off ceiling


@dataclass(frozen=True)
class SimConfig:
    """The simulated payload (sim/payload.py): a pre-rendered loop played in real time."""

    scene: str = "real:1"
    motion: str = "multirotor:60"
    loop_s: float = 2.0
    seed: int = 0
    frame_rate_hz: float = 50.0
    gyro_rate_hz: float = 1000.0
    gyro_noise_rad_s: float = 0.002
    cache_dir: str = ""              # "" = $THERMOD_CACHE (or ~/.cache/thermod), see sim.playback
    ffc_interval_s: float = 0.0      # a flat-field correction (shutter/NUC) every this many s; 0 = never
    ffc_duration_s: float = 0.5      # frames frozen (shutter closed) for this long per FFC
    ffc_step_counts: float = 20.0    # offset step of the new NUC after each FFC (raw counts)


@dataclass(frozen=True)
class PublishConfig:
    endpoint: str = "tcp://127.0.0.1:5555"
    raw: bool = False
    gyro: bool = True
    kernel: bool = True                      # the blur kernel of every deblurred frame (topic "kernel")
    hwm: int = 100
    health_period_s: float = 1.0
    curve_secret_key: str | None = None      # server certificate (*.key_secret) → CURVE encryption
    curve_authorized_keys: str | None = None  # directory of client public certificates (needs the secret key)
    max_queue_mb: float = 128.0              # bytes ZeroMQ may hold for all subscribers together
    allow_insecure_remote: bool = False      # permit a non-loopback bind without CURVE (warned)


@dataclass(frozen=True)
class PipelineConfig:
    workers: int = 0                 # deconvolution threads; 0 = one per core
    job_queue: int = 2               # deblur jobs waiting for a worker (overload drops the oldest)
    frame_ring: int = 32             # frames buffered between the camera thread and the scheduler (~0.6 s)
    gyro_ring_s: float = 10.0        # seconds of gyro history kept
    wait_timeout_s: float = 0.05     # max wait after a frame's time for the gyro to cover it
    reorder_timeout_s: float = 0.5   # max wait to publish frames in order
    watchdog_s: float = 2.0          # a critical thread silent this long stops WATCHDOG=1


@dataclass(frozen=True)
class RtspConfig:
    """``[rtsp]``: the live view served as H.264 over RTSP (`thermod.runtime.rtsp`)."""

    enabled: bool = False
    url: str = "rtsp://127.0.0.1:8554/thermal"
    view: str = "deblurred"          # deblurred | raw | side_by_side (raw left, deblurred right)
    agc_low_pct: float = 1.0         # percentile of the frame mapped to black
    agc_high_pct: float = 99.0       # percentile mapped to white
    agc_smoothing: float = 0.8       # weight of the previous frame's range: no brightness pumping
    colormap: str = ""               # OpenCV colour map name (e.g. "inferno"), "" = grey
    bitrate_kbps: int = 2000
    key_int: int = 10                # frames between key frames: a new client's picture starts within this


@dataclass(frozen=True)
class MonitorConfig:
    """``[monitor]``: the live calibration monitor (`thermod.runtime.monitor`)."""

    enabled: bool = True
    apply: bool = False              # apply a significant, stable estimate that lowers the residual
    cpu_share: float = 0.10          # of one core, at most
    window_s: float = 4.0            # rolling window of frame pairs one estimate is fitted on
    width: int = 320                 # frames are registered at this width (px)
    k_sigma: float = 4.0             # an estimate this many σ from the applied value is significant
    stable_windows: int = 3          # ... in this many consecutive estimates before it is applied


@dataclass(frozen=True)
class LoggingConfig:
    level: str = "info"


@dataclass(frozen=True)
class Config:
    gyro: SourceConfig
    camera: SourceConfig
    sim: SimConfig
    calibration: Calibration
    deblur: DeblurConfig
    publish: PublishConfig
    pipeline: PipelineConfig
    logging: LoggingConfig
    path: str = "<defaults>"
    # counts → °C after deblurring; None = off; CAMERA_RADIOMETRY = the constants the camera reports
    radiometry: radiometrymod.Radiometry | str | None = None
    rtsp: RtspConfig = field(default_factory=RtspConfig)
    monitor: MonitorConfig = field(default_factory=MonitorConfig)

    @property
    def uses_sim(self) -> bool:
        return "sim" in (self.gyro.kind, self.camera.kind)


# ------------------------------------------------------------------------------ sources
def _source(path: str, role: str, table: Any, check_devices: bool):
    """One ``[sources.<role>]`` table, checked against the driver registry's schema for its kind."""
    drivers = sources.REGISTRY[role]
    s = Section(path, f"sources.{role}", table)
    kind = s.pop("kind", None, str, choices=tuple(drivers), required=True)
    dev_kind = drivers[kind].device
    device = None
    if dev_kind == "device file":
        device = s.pop_file("device", required=True, must_exist=check_devices, what="device")
    elif dev_kind == "recording":
        device = s.pop_file("path", required=True, must_exist=True, what="recording")
    elif dev_kind == "id":
        device = s.pop("device", None, str, required=True)
    opts = {}
    for name, o in drivers[kind].options.items():
        opts[name] = s.pop(name, o.default, o.type, lo=o.lo, hi=o.hi, choices=o.choices)
    common = dict(
        poll_timeout_s=s.pop("poll_timeout_s", 0.005, float, lo=0.0005, hi=1.0),
        realtime_priority=s.pop("realtime_priority", 0, int, lo=0, hi=99),
        retry_max_s=s.pop("retry_max_s", 2.0, float, lo=0.01, hi=60.0),
    )
    s.done()
    return SourceConfig(kind=kind, device=device, options=MappingProxyType(opts), **common)


# ------------------------------------------------------------------------------ sections
def _deblur(path: str, table: Any) -> DeblurConfig:
    s = Section(path, "deblur", table)
    d = DeblurConfig()
    kw: dict[str, Any] = dict(
        enabled=s.pop("enabled", d.enabled, bool),
        method=s.pop("method", d.method, str, choices=("kf", "wiener")),
        lam=s.pop("lambda", d.lam, float, lo=0.0, lo_open=True, hi=1e9),
        kernel=s.pop("kernel", d.kernel, str, choices=("thermal", "photon")),
        exposure_s=s.pop("exposure_s", d.exposure_s, float, lo=0.0, lo_open=True, hi=1.0),
        psf=s.pop("psf", d.psf, bool),
        mode=s.pop("mode", d.mode, str, choices=("adaptive", "uniform", "grid")),
        grid_tol_px=s.pop("grid_tol_px", d.grid_tol_px, float, lo=0.05, hi=100.0),
        kf_iterations=s.pop("kf_iterations", d.kf_iterations, int, lo=1, hi=12),
        governor=s.pop("governor", d.governor, bool),
        max_solve_s=s.pop("max_solve_s", d.max_solve_s, float, lo=0.0, lo_open=True, hi=10.0),
        headroom=s.pop("headroom", d.headroom, float, lo=0.0, hi=0.9),
        m=s.pop("m", d.m, float, lo=1.0, hi=20.0),
        min_coverage=s.pop("min_coverage", d.min_coverage, float, lo=0.0, hi=1.0),
        ffc_settle_s=s.pop("ffc_settle_s", d.ffc_settle_s, float, lo=0.0, hi=60.0),
    )
    alpha = s.pop("alpha", d.alpha, float)
    if not (abs(alpha - 1.0) < 1e-9 or abs(alpha - 2.0 / 3.0) < 1e-3):
        raise s.fail("alpha", "1 or 2/3 (0.667) — the exponents with a closed-form w-step", alpha)
    kw["alpha"] = 1.0 if abs(alpha - 1.0) < 1e-9 else 2.0 / 3.0
    if s.has("grid"):
        g = s.t.pop("grid")
        if not (isinstance(g, list) and len(g) == 2 and all(isinstance(x, int) and not isinstance(x, bool)
                                                            and 1 <= x <= 16 for x in g)):
            raise s.fail("grid", "[rows, cols], integers in [1, 16]", g)
        kw["grid"] = (g[0], g[1])
    s.done()
    return DeblurConfig(**kw)


def _publish(path: str, table: Any) -> PublishConfig:
    s = Section(path, "publish", table)
    d = PublishConfig()
    from thermod.runtime.endpoints import endpoint_problem, is_loopback
    endpoint = s.pop("endpoint", d.endpoint, str)
    if (problem := endpoint_problem(endpoint)) is not None:
        raise s.fail("endpoint", "a ZeroMQ endpoint like 'tcp://127.0.0.1:5555' or "
                     f"'ipc:///run/thermod.sock' ({problem})", endpoint)
    kw = dict(endpoint=endpoint, raw=s.pop("raw", d.raw, bool), gyro=s.pop("gyro", d.gyro, bool),
              kernel=s.pop("kernel", d.kernel, bool),
              hwm=s.pop("hwm", d.hwm, int, lo=1, hi=1_000_000),
              health_period_s=s.pop("health_period_s", d.health_period_s, float, lo=0.05, hi=60.0),
              curve_secret_key=s.pop_file("curve_secret_key", what="CURVE key file"),
              curve_authorized_keys=s.pop_file("curve_authorized_keys", what="directory"),
              max_queue_mb=s.pop("max_queue_mb", d.max_queue_mb, float, lo=1.0, hi=65536.0),
              allow_insecure_remote=s.pop("allow_insecure_remote", d.allow_insecure_remote, bool))
    if not is_loopback(endpoint) and kw["curve_secret_key"] is None and not kw["allow_insecure_remote"]:
        raise s.fail("endpoint", "a loopback or ipc:// address, or publish.curve_secret_key for CURVE, or "
                     "publish.allow_insecure_remote = true (the stream would be readable by anyone on the "
                     "network)", endpoint)
    if kw["curve_authorized_keys"] is not None and kw["curve_secret_key"] is None:
        raise ConfigError(f"{path}: publish.curve_secret_key: missing (curve_authorized_keys needs the "
                          "server's secret key file)")
    s.done()
    return PublishConfig(**kw)


def _pipeline(path: str, table: Any) -> PipelineConfig:
    s = Section(path, "pipeline", table)
    d = PipelineConfig()
    kw = dict(workers=s.pop("workers", d.workers, int, lo=0, hi=64),
              job_queue=s.pop("job_queue", d.job_queue, int, lo=1, hi=64),
              frame_ring=s.pop("frame_ring", d.frame_ring, int, lo=2, hi=1024),
              gyro_ring_s=s.pop("gyro_ring_s", d.gyro_ring_s, float, lo=0.5, hi=600.0),
              wait_timeout_s=s.pop("wait_timeout_s", d.wait_timeout_s, float, lo=0.0, hi=2.0),
              reorder_timeout_s=s.pop("reorder_timeout_s", d.reorder_timeout_s, float, lo=0.0, hi=10.0),
              watchdog_s=s.pop("watchdog_s", d.watchdog_s, float, lo=0.1, hi=600.0))
    s.done()
    return PipelineConfig(**kw)


def _sim(path: str, table: Any) -> SimConfig:
    s = Section(path, "sim", table)
    d = SimConfig()
    kw = dict(scene=s.pop("scene", d.scene, str), motion=s.pop("motion", d.motion, str),
              loop_s=s.pop("loop_s", d.loop_s, float, lo=0.2, hi=120.0),
              seed=s.pop("seed", d.seed, int, lo=0),
              frame_rate_hz=s.pop("frame_rate_hz", d.frame_rate_hz, float, lo=1.0, hi=500.0),
              gyro_rate_hz=s.pop("gyro_rate_hz", d.gyro_rate_hz, float, choices=(1000.0, 2000.0, 4000.0)),
              gyro_noise_rad_s=s.pop("gyro_noise_rad_s", d.gyro_noise_rad_s, float, lo=0.0, hi=1.0),
              cache_dir=s.pop("cache_dir", d.cache_dir, str),
              ffc_interval_s=s.pop("ffc_interval_s", d.ffc_interval_s, float, lo=0.0, hi=86400.0),
              ffc_duration_s=s.pop("ffc_duration_s", d.ffc_duration_s, float, lo=0.0, lo_open=True, hi=10.0),
              ffc_step_counts=s.pop("ffc_step_counts", d.ffc_step_counts, float, lo=-1000.0, hi=1000.0))
    if 0 < kw["ffc_interval_s"] <= kw["ffc_duration_s"]:
        dur = kw["ffc_duration_s"]
        raise s.fail("ffc_interval_s", f"0 (never) or longer than ffc_duration_s ({dur:g} s)",
                     kw["ffc_interval_s"])
    s.done()
    return SimConfig(**kw)


def _rtsp(path: str, table: Any) -> RtspConfig:
    from thermod.runtime.rtsp import COLORMAPS, VIEWS, RtspError, parse_url
    s = Section(path, "rtsp", table)
    d = RtspConfig()
    url = s.pop("url", d.url, str)
    try:
        parse_url(url)
    except RtspError as e:
        raise ConfigError(f"{path}: rtsp.url: {e}") from None
    kw = dict(enabled=s.pop("enabled", d.enabled, bool), url=url,
              view=s.pop("view", d.view, str, choices=VIEWS),
              agc_low_pct=s.pop("agc_low_pct", d.agc_low_pct, float, lo=0.0, hi=50.0),
              agc_high_pct=s.pop("agc_high_pct", d.agc_high_pct, float, lo=50.0, hi=100.0),
              agc_smoothing=s.pop("agc_smoothing", d.agc_smoothing, float, lo=0.0, hi=0.99),
              colormap=s.pop("colormap", d.colormap, str, choices=COLORMAPS),
              bitrate_kbps=s.pop("bitrate_kbps", d.bitrate_kbps, int, lo=50, hi=100_000),
              key_int=s.pop("key_int", d.key_int, int, lo=1, hi=1000))
    if kw["agc_low_pct"] >= kw["agc_high_pct"]:
        raise s.fail("agc_high_pct", f"a value above agc_low_pct ({kw['agc_low_pct']})", kw["agc_high_pct"])
    s.done()
    return RtspConfig(**kw)


def _monitor(path: str, table: Any) -> MonitorConfig:
    s = Section(path, "monitor", table)
    d = MonitorConfig()
    kw = dict(enabled=s.pop("enabled", d.enabled, bool), apply=s.pop("apply", d.apply, bool),
              cpu_share=s.pop("cpu_share", d.cpu_share, float, lo=0.001, hi=1.0),
              window_s=s.pop("window_s", d.window_s, float, lo=0.5, hi=60.0),
              width=s.pop("width", d.width, int, lo=32, hi=1024),
              k_sigma=s.pop("k_sigma", d.k_sigma, float, lo=1.0, hi=100.0),
              stable_windows=s.pop("stable_windows", d.stable_windows, int, lo=1, hi=100))
    s.done()
    return MonitorConfig(**kw)


def _logging(path: str, table: Any) -> LoggingConfig:
    s = Section(path, "logging", table)
    lvl = s.pop("level", "info", str, choices=("debug", "info", "warning", "error"))
    s.done()
    return LoggingConfig(level=lvl)


CAMERA_RADIOMETRY = "camera"     # [radiometry] model = "camera": the Planck constants the camera reports


def _radiometry(path: str, table: Any) -> radiometrymod.Radiometry | str | None:
    """A ``[radiometry]`` table: model = "none" | "planck" (R, B, F, O) | "linear" (gain, offset) |
    "camera" (the constants the camera itself reports, read once it streams: `CAMERA_RADIOMETRY`)."""
    s = Section(path, "radiometry", table)
    model = s.pop("model", "none", str, choices=("none", *radiometrymod.MODELS, CAMERA_RADIOMETRY))
    if model == CAMERA_RADIOMETRY:
        s.done()
        return CAMERA_RADIOMETRY
    kw: dict[str, Any] = {"model": model}
    for k in [k for k in s.t if k in ("R", "B", "F", "O", "gain", "offset")]:
        kw[k] = s.pop(k, None, float)
    try:
        return radiometrymod.from_mapping({**kw, **s.t})  # left-over keys: named as unknown there
    except radiometrymod.RadiometryError as e:
        raise ConfigError(f"{path}: radiometry.{e.field}: {e.problem}") from None


def load_radiometry(path: str | os.PathLike) -> radiometrymod.Radiometry | None:
    """The [radiometry] table of a TOML file (a full configuration or a small model file), validated as in
    `load`; None when the file has no such table or says model = "none". Offline there is no camera to
    ask, so model = "camera" is an error here."""
    p = Path(path)
    raw = read_toml(p)
    model = _radiometry(str(p), raw["radiometry"]) if "radiometry" in raw else None
    if model == CAMERA_RADIOMETRY:
        raise ConfigError(f"{p}: radiometry.model: 'camera' needs a live camera; give 'planck' constants "
                          "(R, B, F, O) or 'linear' (gain, offset) for offline use")
    return model


# ------------------------------------------------------------------------------ entry points
def default_path() -> Path:
    """The packaged default configuration (the simulated payload)."""
    return Path(str(resources.files("thermod.configs").joinpath("sim.toml")))


def _apply_override(path: str, raw: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = raw
    for i, p in enumerate(parts[:-1]):
        nxt = node.setdefault(p, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"{path}: {'.'.join(parts[:i + 1])}: expected a table to override {dotted!r}")
        node = nxt
    node[parts[-1]] = value


def parse(raw: dict, path: str = "<memory>", *, check_devices: bool = True) -> Config:
    """Validate an already-parsed TOML document."""
    top = Section(path, "", raw)
    src = Section(path, "sources", top.t.pop("sources", {}))
    if not src.has("gyro") or not src.has("camera"):
        missing = "sources.gyro" if not src.has("gyro") else "sources.camera"
        raise ConfigError(f"{path}: {missing}: missing (expected a table with `kind = ...`)")
    gyro = _source(path, "gyro", src.t.pop("gyro"), check_devices)
    camera = _source(path, "camera", src.t.pop("camera"), check_devices)
    src.done()
    if top.has("sim") and "sim" not in (gyro.kind, camera.kind):
        raise ConfigError(f"{path}: sim: only allowed when a source has kind = 'sim'")
    cfg = Config(
        gyro=gyro, camera=camera,
        sim=_sim(path, top.t.pop("sim", {})),
        calibration=calibration_from_table(path, top.t.pop("calibration", {})),
        deblur=_deblur(path, top.t.pop("deblur", {})),
        publish=_publish(path, top.t.pop("publish", {})),
        pipeline=_pipeline(path, top.t.pop("pipeline", {})),
        logging=_logging(path, top.t.pop("logging", {})),
        path=path,
        radiometry=_radiometry(path, top.t.pop("radiometry", {})),
        rtsp=_rtsp(path, top.t.pop("rtsp", {})),
        monitor=_monitor(path, top.t.pop("monitor", {})),
    )
    top.done()
    if cfg.uses_sim:
        c, s = cfg.calibration, cfg.sim
        if abs(c.frame_rate_hz - s.frame_rate_hz) > 1e-9 or abs(c.rate_hz - s.gyro_rate_hz) > 1e-9:
            raise ConfigError(f"{path}: calibration.frame_rate_hz/rate_hz: expected to match "
                              f"sim.frame_rate_hz ({s.frame_rate_hz}) and sim.gyro_rate_hz "
                              f"({s.gyro_rate_hz})")
    return cfg


def load(path: str | os.PathLike | None = None, overrides: dict[str, Any] | None = None, *,
         check_devices: bool = True) -> Config:
    """Read and validate a TOML configuration (None = the packaged simulated-payload default).

    `overrides` maps dotted keys to values applied before validation ({"publish.endpoint": ...}).
    `check_devices=False` skips the existence check of device nodes (for inspecting a hardware
    configuration on another machine); recordings and key files are always checked.
    """
    p = default_path() if path is None else Path(path)
    name, raw = str(p), read_toml(p)
    for k, v in (overrides or {}).items():
        _apply_override(name, raw, k, v)
    return parse(raw, name, check_devices=check_devices)


def parse_override(text: str) -> tuple[str, Any]:
    """``"deblur.lambda=3000"`` → ("deblur.lambda", 3000.0); the value is a TOML literal, or a bare string."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE, e.g. deblur.method=wiener")
    k, v = text.split("=", 1)
    k = k.strip()
    try:
        val = tomllib.loads(f"v = {v.strip()}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):
        val = v.strip()
    return k, val
