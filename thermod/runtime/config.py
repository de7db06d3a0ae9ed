"""Daemon configuration: TOML (tomllib) → validated, frozen dataclasses.

Each section's keys are declared once, on its dataclass, with `setting` (type, default, range or
choices, doc); `parse` reads every section through `thermod.io.toml_tables.Section.read`. A new
section is a dataclass declared that way plus one `section(...)` field of `Config`.

Every problem (unknown key, wrong type, out-of-range value, missing device or key file) is collected,
and one `ConfigError` lists them all, each naming its source (the file, or the ``--set KEY=VALUE`` that
gave the value), the dotted key (e.g. ``deblur.lambda``) and what was expected; an unknown key comes
with the nearest known one. `load(None)` reads the packaged default, ``thermod.configs/sim.toml`` (the
simulated payload). `overrides` ({dotted key: value}) are applied on top of the file before validation,
so command-line settings get the same checks as the file.

Sections: ``[sources.gyro]``, ``[sources.camera]`` (options from the driver registry,
`thermod.runtime.sources`), ``[sim]`` (only with a simulated source), ``[calibration]``
(→ `thermod.physics.calibration.Calibration`), ``[deblur]``, ``[publish]``, ``[pipeline]``,
``[logging]``, ``[radiometry]`` (→ `thermod.physics.radiometry`; model "none" by default), ``[rtsp]``
(the H.264 live view, `thermod.runtime.rtsp`), ``[monitor]`` (the live calibration monitor,
`thermod.runtime.monitor`).
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

from thermod.errors import ConfigError
from thermod.io import endpoints
from thermod.io.calibration_file import calibration_from_table
from thermod.io.toml_tables import (
    REQUIRED,
    Key,
    Problems,
    Section,
    read_toml,
    schema_of,
    setting,
)
from thermod.io.toml_tables import reference as toml_reference
from thermod.physics import radiometry as radiometrymod
from thermod.physics.calibration import Calibration
from thermod.physics.detector import DEFAULT_NETD_K
from thermod.restore.settings import DEBLUR, DeblurConfig, read_deblur
from thermod.runtime import sources


def section(cls) -> Any:
    """A `Config` field holding the ``[name]`` table read against `cls`'s schema (absent → defaults)."""
    return field(default_factory=cls, metadata={"section": cls})


def _endpoint_rule(v: str) -> str | None:
    problem = endpoints.endpoint_problem(v)
    return None if problem is None else \
        f"a ZeroMQ endpoint like 'tcp://127.0.0.1:5555' or 'ipc:///run/thermod.sock' ({problem})"


# ------------------------------------------------------------------------------ dataclasses
@dataclass(frozen=True)
class SourceConfig:
    """One device. `device` is the device node / sysfs dir / port / recording path / camera id the
    driver opens (None for `sim`); `options` are the kind's remaining parameters (read-only)."""

    kind: str
    device: str | None = None
    options: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    poll_timeout_s: float = setting(0.005, lo=0.0005, hi=1.0, doc="longest wait of one driver poll")
    realtime_priority: int = setting(0, lo=0, hi=99, doc="SCHED_FIFO priority of the driver; 0 = normal")
    retry_max_s: float = setting(2.0, lo=0.01, hi=60.0, doc="reconnect back-off ceiling")

    # pickled into the gyro process (`thermod.runtime.gyro_process`): the read-only options as a dict
    def __getstate__(self) -> dict:
        return {**self.__dict__, "options": dict(self.options)}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update({**state, "options": MappingProxyType(state["options"])})


@dataclass(frozen=True)
class SimConfig:
    """The simulated payload (sim/payload.py): a pre-rendered loop played in real time."""

    scene: str = setting("real:1", doc="real:N (a thermal PNG of the data set) or a procedural scene")
    motion: str = setting("multirotor:60", doc="a thermod.sim.motion spec (multirotor: RMS roll rate °/s)")
    loop_s: float = setting(2.0, lo=0.2, hi=120.0, doc="length of the pre-rendered loop")
    seed: int = setting(0, lo=0)
    frame_rate_hz: float = setting(50.0, lo=1.0, hi=500.0)
    gyro_rate_hz: float = setting(1000.0, choices=(1000.0, 2000.0, 4000.0))
    gyro_noise_rad_s: float = setting(0.002, lo=0.0, hi=1.0)
    tau_s: float = setting(0.0, lo=0.0, hi=1.0,
                           doc="the simulated camera's true thermal time constant (s); 0 = [calibration]'s")
    netd_k: float = setting(DEFAULT_NETD_K, lo=0.0, hi=10.0,
                            doc="the simulated camera's temporal noise (NETD, K RMS; 0 = noiseless)")
    cache_dir: str = setting("", doc='"" = thermod.paths.cache_dir() ($XDG_CACHE_HOME/thermod)',
                             rule=lambda v: "a directory path without NUL characters" if "\0" in v else None,
                             accepts="a directory path")
    ffc_interval_s: float = setting(0.0, lo=0.0, hi=86400.0,
                                    doc="a flat-field correction (shutter/NUC) every this many s; 0 = never")
    ffc_duration_s: float = setting(0.5, lo=0.0, lo_open=True, hi=10.0,
                                    doc="frames frozen (shutter closed) for this long per FFC")
    ffc_step_counts: float = setting(20.0, lo=-1000.0, hi=1000.0,
                                     doc="offset step of the new NUC after each FFC (raw counts)")

    def problems(self) -> Iterator[tuple[str, str]]:
        if 0 < self.tau_s < 1e-6:
            yield "tau_s", f"expected 0 (the calibration's) or at least 1e-6 s, got {self.tau_s!r}"
        if 0 < self.ffc_interval_s <= self.ffc_duration_s:
            yield "ffc_interval_s", (f"expected 0 (never) or longer than ffc_duration_s "
                                     f"({self.ffc_duration_s:g} s), got {self.ffc_interval_s!r}")


@dataclass(frozen=True)
class PublishConfig:
    endpoint: str = setting(endpoints.DEFAULT_ENDPOINT, rule=_endpoint_rule,
                            accepts="tcp://HOST:PORT, ipc://PATH or inproc://NAME")
    raw: bool = setting(False, doc="publish the raw frames too (topic raw)")
    gyro: bool = setting(True)
    gyro_batch_s: float = setting(0.05, lo=0.0, hi=1.0,
                                  doc="gyro samples coalesced into one message for up to this long (s)")
    kernel: bool = setting(True, doc="the blur kernel of every deblurred frame (topic kernel)")
    hwm: int = setting(endpoints.DEFAULT_HWM, lo=1, hi=1_000_000, doc="messages queued per subscriber")
    health_period_s: float = setting(1.0, lo=0.05, hi=60.0)
    curve_secret_key: str | None = setting(None, str, file="CURVE key file",
                                           doc="server certificate (*.key_secret) → CURVE encryption")
    curve_authorized_keys: str | None = setting(None, str, file="directory",
                                                doc="directory of client public certificates")
    max_queue_mb: float = setting(endpoints.DEFAULT_MAX_QUEUE_BYTES / 2**20, lo=1.0, hi=65536.0,
                                  doc="bytes ZeroMQ may hold for all subscribers together")
    allow_insecure_remote: bool = setting(False, doc="permit a non-loopback bind without CURVE (warned)")

    def problems(self) -> Iterator[tuple[str, str]]:
        bad = endpoints.security_problem(self.endpoint, self.curve_secret_key is not None,
                                         self.curve_authorized_keys is not None, self.allow_insecure_remote)
        if bad is not None:
            yield bad


@dataclass(frozen=True)
class PipelineConfig:
    workers: int = setting(0, lo=0, hi=64, doc="workers; 0 = one per usable core (quota-capped)")
    processes: bool = setting(True, doc="each worker solves in a child process of its own (a GIL of its "
                                        "own; about 190 MB more memory each); false: in the worker thread")
    job_queue: int = setting(4, lo=1, hi=64, doc="deblur jobs waiting for a worker (overload drops oldest)")
    frame_ring: int = setting(32, lo=2, hi=1024, doc="frames buffered between camera thread and scheduler")
    gyro_ring_s: float = setting(30.0, lo=0.5, hi=600.0,
                                 doc="seconds of gyro history kept (a settled monitor fits over this less 2)")
    wait_timeout_s: float = setting(0.05, lo=0.0, hi=2.0,
                                    doc="max wait after a frame's time for the gyro to cover it")
    reorder_timeout_s: float = setting(0.5, lo=0.0, hi=10.0, doc="max wait to publish frames in order")
    watchdog_s: float = setting(2.0, lo=0.1, hi=600.0, doc="a thread silent this long stops WATCHDOG=1")


# the live view's pictures, and the OpenCV colour maps offered by name (cv2.COLORMAP_<NAME>); "" = grey
VIEWS = ("deblurred", "raw", "side_by_side")
COLORMAPS = ("", "autumn", "bone", "jet", "winter", "rainbow", "ocean", "summer", "spring", "cool", "hsv",
             "pink", "hot", "parula", "magma", "inferno", "plasma", "viridis", "cividis", "twilight",
             "turbo", "deepgreen")


@dataclass(frozen=True)
class RtspConfig:
    """``[rtsp]``: the live view served as H.264 over RTSP (`thermod.runtime.rtsp`)."""

    enabled: bool = setting(False)
    url: str = setting(endpoints.DEFAULT_RTSP_URL, rule=endpoints.rtsp_url_problem,
                       accepts="rtsp://HOST:PORT/PATH")
    view: str = setting("deblurred", choices=VIEWS, doc="side_by_side: raw left, deblurred right")
    agc_low_pct: float = setting(1.0, lo=0.0, hi=50.0, doc="percentile of the frame mapped to black")
    agc_high_pct: float = setting(99.0, lo=50.0, hi=100.0, doc="percentile mapped to white")
    agc_smoothing: float = setting(0.8, lo=0.0, hi=0.99,
                                   doc="weight of the previous frame's range: no brightness pumping")
    colormap: str = setting("", choices=COLORMAPS, doc='OpenCV colour map name, "" = grey')
    bitrate_kbps: int = setting(2000, lo=50, hi=100_000)
    key_int: int = setting(10, lo=1, hi=1000,
                           doc="frames between key frames: a new client's picture starts within this")

    def problems(self) -> Iterator[tuple[str, str]]:
        if self.agc_low_pct >= self.agc_high_pct:
            yield "agc_high_pct", (f"expected a value above agc_low_pct ({self.agc_low_pct}), "
                                   f"got {self.agc_high_pct!r}")


@dataclass(frozen=True)
class MonitorConfig:
    """``[monitor]``: the live calibration monitor (`thermod.runtime.monitor`)."""

    enabled: bool = setting(True)
    apply: bool = setting(False, doc="apply a significant, stable estimate that lowers the residual")
    cpu_share: float = setting(0.05, lo=0.001, hi=1.0, doc="the share of one core it may use, at most")
    settled_cpu_share: float = setting(
        0.01, lo=0.001, hi=1.0, doc="its share, at most, once `stable_windows` fits in a row agree with "
        "the calibration in force (it then watches for drift over windows stretched by the shares' ratio)")
    window_s: float = setting(4.0, lo=0.5, hi=60.0,
                              doc="rolling window of frame pairs one estimate is fitted on")
    max_window_s: float = setting(60.0, lo=1.0, hi=600.0,
                                  doc="the longest its windows stretch to hold a fit's pairs when they come "
                                  "sparsely (s; the motion's also within the gyro history)")
    width: int = setting(320, lo=32, hi=1024,
                         doc="frames are registered at this width (px; at most the frame's)")
    k_sigma: float = setting(4.0, lo=1.0, hi=100.0,
                             doc="an estimate this many sigma from the applied value is significant")
    stable_windows: int = setting(3, lo=1, hi=100,
                                  doc="consecutive significant estimates before one is applied")


@dataclass(frozen=True)
class LoggingConfig:
    level: str = setting("info", choices=("debug", "info", "warning", "error"))


@dataclass(frozen=True)
class Config:
    gyro: SourceConfig
    camera: SourceConfig
    calibration: Calibration
    deblur: DeblurConfig
    path: str = "<defaults>"
    # counts → °C after deblurring; None = off; CAMERA_RADIOMETRY = the constants the camera reports
    radiometry: radiometrymod.Radiometry | str | None = None
    sim: SimConfig = section(SimConfig)
    publish: PublishConfig = section(PublishConfig)
    pipeline: PipelineConfig = section(PipelineConfig)
    logging: LoggingConfig = section(LoggingConfig)
    rtsp: RtspConfig = section(RtspConfig)
    monitor: MonitorConfig = section(MonitorConfig)

    @property
    def uses_sim(self) -> bool:
        return "sim" in (self.gyro.kind, self.camera.kind)


# ------------------------------------------------------------------------------ sections
def read_section(problems: Problems, name: str, table: Any, cls):
    """The ``[name]`` table as a `cls` (declared with `setting`); bad keys are recorded in `problems`
    and keep their defaults, and the dataclass's own cross-key `problems()` run when its keys are sound."""
    s = Section(problems, name, table)
    obj = cls(**s.read(schema_of(cls)))
    s.done()
    if s.ok and hasattr(obj, "problems"):
        for key, text in obj.problems():
            s.problem(key, text)
    return obj


def _source(problems: Problems, role: str, table: Any, check_devices: bool) -> SourceConfig:
    """One ``[sources.<role>]`` table, checked against the driver registry's schema for its kind."""
    drivers = sources.REGISTRY[role]
    s = Section(problems, f"sources.{role}", table)
    kind = s.get("kind", Key(str, REQUIRED, choices=tuple(drivers)))
    if kind is None:                     # without a kind there is no schema for the rest
        return SourceConfig(kind="sim")
    dev_kind = drivers[kind].device
    device = None
    if dev_kind == "device file":
        device = s.pop_file("device", required=True, must_exist=check_devices, what="device")
    elif dev_kind == "recording":
        device = s.pop_file("path", required=True, must_exist=True, what="recording")
    elif dev_kind == "id":
        device = s.get("device", Key(str, REQUIRED))
    opts = s.read(drivers[kind].options)
    common = s.read(schema_of(SourceConfig))
    s.done()
    return SourceConfig(kind=kind, device=device, options=MappingProxyType(opts), **common)


CAMERA_RADIOMETRY = "camera"     # [radiometry] model = "camera": the Planck constants the camera reports


def _radiometry(problems: Problems, table: Any) -> radiometrymod.Radiometry | str | None:
    """A ``[radiometry]`` table: model = "none" | "planck" (R, B, F, O) | "linear" (gain, offset) |
    "camera" (the constants the camera itself reports, read once it streams: `CAMERA_RADIOMETRY`)."""
    s = Section(problems, "radiometry", table)
    model = s.get("model", Key(str, "none", choices=("none", *radiometrymod.MODELS, CAMERA_RADIOMETRY)))
    if model == CAMERA_RADIOMETRY or not s.ok:
        s.done()
        return CAMERA_RADIOMETRY if model == CAMERA_RADIOMETRY else None
    kw: dict[str, Any] = {"model": model}
    for k in [k for k in s.t if k in ("R", "B", "F", "O", "gain", "offset")]:
        kw[k] = s.get(k, Key(float))
    if not s.ok:
        return None
    try:
        return radiometrymod.from_mapping({**kw, **s.t})  # left-over keys: named as unknown there
    except radiometrymod.RadiometryError as e:
        s.problem(e.field, e.problem)
        return None


def load_radiometry(path: str | os.PathLike) -> radiometrymod.Radiometry | None:
    """The [radiometry] table of a TOML file (a full configuration or a small model file), validated as in
    `load`; None when the file has no such table or says model = "none". Offline there is no camera to
    ask, so model = "camera" is an error here."""
    p = Path(path)
    raw = read_toml(p)
    problems = Problems(str(p))
    model = _radiometry(problems, raw["radiometry"]) if "radiometry" in raw else None
    problems.raise_if_any()
    if model == CAMERA_RADIOMETRY:
        raise ConfigError(f"{p}: radiometry.model: 'camera' needs a live camera; give 'planck' constants "
                          "(R, B, F, O) or 'linear' (gain, offset) for offline use")
    return model


def reference() -> str:
    """Every key of the configuration with its default, meaning and allowed values, as a TOML document
    (`thermod run --list-keys`), generated from the schemas the loader checks against."""
    from thermod.io.calibration_file import SCHEMA as CALIBRATION

    out = []
    for role, drivers in sources.REGISTRY.items():
        out += [f"[sources.{role}]", f"kind = ...  # one of {', '.join(repr(k) for k in drivers)}"]
        out += reference_lines(schema_of(SourceConfig))
        for kind, d in drivers.items():
            device = {"device file": "device = PATH", "recording": "path = RECORDING",
                      "id": "device = ID"}.get(d.device or "", "")
            if device or d.options:
                out.append(f"#   kind = {kind!r}: {device or 'no device'}")
                out += ["#   " + ln for ln in reference_lines(d.options)]
        out.append("")
    calibration = {k: dataclasses.replace(key, default=getattr(Calibration(), k))
                   for k, key in CALIBRATION.items()}
    tables = {**{name: schema_of(cls) for name, cls in _config_sections().items()}, "deblur": DEBLUR,
              "calibration": calibration}
    for name, schema in tables.items():
        out += toml_reference(name, schema)
        if name == "calibration":
            out += ["# cx, cy = the image centre  # principal point (px)",
                    "# readout_s = 0.0  # rolling-shutter readout, at most one frame period",
                    "# R_cam_gyro = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]  # gyro → camera rotation"]
        out.append("")
    models = ", ".join(repr(m) for m in ("none", *radiometrymod.MODELS, CAMERA_RADIOMETRY))
    out += ["[radiometry]", f'model = "none"  # one of {models}; planck: R, B, F, O; linear: gain, offset']
    return "\n".join(out) + "\n"


def reference_lines(schema: Mapping[str, Key]) -> list[str]:
    return toml_reference("", schema)[1:]


# ------------------------------------------------------------------------------ entry points
def default_path() -> Path:
    """The packaged default configuration (the simulated payload)."""
    return Path(str(resources.files("thermod.configs").joinpath("sim.toml")))


def _apply_override(problems: Problems, raw: dict, dotted: str, value: Any) -> list[str]:
    """Set dotted key `dotted` of `raw` to `value`; the tables it had to create (their problems are the
    override's, not the file's)."""
    parts = dotted.split(".")
    if not all(p.strip() for p in parts):
        problems.add(dotted, "expected a dotted key like deblur.lambda (no empty parts)")
        return []
    node, created = raw, []
    for i, p in enumerate(parts[:-1]):
        if p not in node:
            created.append(".".join(parts[:i + 1]))
        nxt = node.setdefault(p, {})
        if not isinstance(nxt, dict):
            problems.add(dotted, f"{'.'.join(parts[:i + 1])} is not a table, so it has no key {parts[-1]!r}")
            return created
        node = nxt
    node[parts[-1]] = value
    return created


def override_text(key: str, value: Any) -> str:
    """How the command line gave `key`: ``--set KEY=VALUE`` (the value as a TOML literal)."""
    if isinstance(value, bool):
        lit = "true" if value else "false"
    elif isinstance(value, str):
        try:
            lit = value if not isinstance(tomllib.loads(f"v = {value}")["v"], str) else repr(value)
        except (tomllib.TOMLDecodeError, RecursionError):
            lit = value if value.isprintable() else repr(value)    # a bare string, as typed
    else:
        lit = repr(value) if not isinstance(value, list) else str(value)
    return f"--set {key}={lit}"


def _config_sections() -> dict[str, type]:
    """TOML table → dataclass of every `section(...)` field of `Config`."""
    return {f.name: f.metadata["section"] for f in dataclasses.fields(Config) if "section" in f.metadata}


def parse(raw: dict, path: str = "<memory>", *, check_devices: bool = True,
          origins: Mapping[str, str] | None = None) -> Config:
    """Validate an already-parsed TOML document; one ConfigError lists every problem. `origins` maps the
    dotted keys that did not come from `path` to where they came from (``--set KEY=VALUE``)."""
    problems = Problems(path, origins)
    top = Section(problems, "", raw)
    src = Section(problems, "sources", top.take("sources") if top.has("sources") else {})
    roles = {}
    for role in ("gyro", "camera"):
        if src.has(role):
            roles[role] = _source(problems, role, src.take(role), check_devices)
        else:
            if "" not in src.bad:        # ([sources] itself not a table is the one problem to report)
                src.problem(role, "missing (expected a table with `kind = ...`)")
            roles[role] = SourceConfig(kind="sim")
    src.done()
    uses_sim = "sim" in (roles["gyro"].kind, roles["camera"].kind)
    if top.has("sim") and not uses_sim and src.ok:
        top.problem("sim", "only allowed when a source has kind = 'sim'")
    tables = {name: read_section(problems, name, top.take(name) if top.has(name) else {}, cls)
              for name, cls in _config_sections().items()}
    calibration = calibration_from_table(problems, top.take("calibration") if top.has("calibration") else {})
    deblur = read_deblur(problems, top.take("deblur") if top.has("deblur") else {})
    radiometry = _radiometry(problems, top.take("radiometry") if top.has("radiometry") else {})
    top.done()
    spec_keys = ("sim", "sim.scene", "sim.motion", "sim.loop_s", "sim.seed")   # what the check reads
    if uses_sim and not any(k in spec_keys for k, _ in problems.items):
        for key, text in sources.sim_problems(tables["sim"]):
            problems.add(f"sim.{key}", text)
    if uses_sim and not problems.items:
        c, s = calibration, tables["sim"]
        if abs(c.frame_rate_hz - s.frame_rate_hz) > 1e-9 or abs(c.rate_hz - s.gyro_rate_hz) > 1e-9:
            problems.add("calibration.frame_rate_hz/rate_hz", f"expected to match sim.frame_rate_hz "
                         f"({s.frame_rate_hz}) and sim.gyro_rate_hz ({s.gyro_rate_hz})")
    problems.raise_if_any()
    return Config(gyro=roles["gyro"], camera=roles["camera"], calibration=calibration, deblur=deblur,
                  path=path, radiometry=radiometry, **tables)


def load(path: str | os.PathLike | None = None, overrides: dict[str, Any] | None = None, *,
         check_devices: bool = True, origins: Mapping[str, str] | None = None) -> Config:
    """Read and validate a TOML configuration (None = the packaged simulated-payload default).

    `overrides` maps dotted keys to values applied before validation ({"publish.endpoint": ...}); a
    problem with one names ``--set KEY=VALUE`` (or what `origins` says gave that key, e.g.
    ``--endpoint EP``), not the file. `check_devices=False` skips the existence
    check of device nodes (for inspecting a hardware configuration on another machine); recordings and
    key files are always checked.
    """
    p = default_path() if path is None else Path(path)
    name, raw = str(p), read_toml(p)
    origins = {**{k: override_text(k, v) for k, v in (overrides or {}).items()}, **(origins or {})}
    problems = Problems(name, origins)
    for k, v in (overrides or {}).items():
        for table in _apply_override(problems, raw, k, v):
            origins.setdefault(table, origins[k])
    problems.raise_if_any()
    return parse(raw, name, check_devices=check_devices, origins=origins)


def parse_override(text: str) -> tuple[str, Any]:
    """``"deblur.lambda=3000"`` → ("deblur.lambda", 3000.0); the value is a TOML literal, or a bare string."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE, e.g. deblur.method=wiener")
    k, v = text.split("=", 1)
    k = k.strip()
    if not all(p.strip() for p in k.split(".")):
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE with KEY a dotted key, "
                          "e.g. deblur.method=wiener")
    try:
        val = tomllib.loads(f"v = {v.strip()}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):
        val = v.strip()
    return k, val
