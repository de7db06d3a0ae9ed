"""Fuzzing the configuration loader (Hypothesis, bounded for CI): random byte strings, the shipped
configurations with bytes flipped, inserted or cut, random TOML documents, and the shipped
configurations with one key set to a random TOML value. Whatever the input, `config.load` and
`config.parse` either return a Config or raise ConfigError naming the file — nothing else escapes."""

import dataclasses
import datetime as dt
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from thermod.errors import ConfigError
from thermod.io import toml_tables
from thermod.physics.calibration import Calibration
from thermod.runtime import config

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
SHIPPED = {p.name: p.read_bytes() for p in sorted(CONFIG_DIR.glob("*.toml"))}
FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
NAME = "fuzzed.toml"


def load_bytes(data: bytes):
    """`config.load` on a real file holding `data` (reading, decoding, parsing and validation)."""
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / NAME
        p.write_bytes(data)
        try:
            return config.load(p, check_devices=False)
        except ConfigError as e:
            assert str(e).startswith(str(p) + ":"), str(e)      # the message names the file first
            raise


def only_config_error(fn, *args):
    try:
        fn(*args)
    except ConfigError:
        pass


# ------------------------------------------------------------------------------ TOML values
def _toml_str(s: str) -> str:
    out = []
    for ch in s:
        if ch in '"\\' or ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def toml_value(v) -> str:
    """A TOML literal for a Python value (enough of TOML 1.0 for what `values` generates)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, (dt.datetime, dt.date, dt.time)):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_str(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


keys = st.sampled_from(["kind", "device", "path", "width", "height", "tau_s", "lambda", "grid", "endpoint",
                        "R_cam_gyro", "scale", "bias_rad_s", "workers", "seed", "x"]) | st.text(max_size=6)
scalars = (st.booleans() | st.integers(-2**63, 2**63 - 1) | st.floats(allow_nan=True, allow_infinity=True)
           | st.text(max_size=12) | st.sampled_from(["sim", "replay", "kf", "/dev/null", "tcp://127.0.0.1:1"])
           | st.dates() | st.times() | st.datetimes())
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(keys, inner,
                                                                                            max_size=3),
                      max_leaves=12)
sections = st.sampled_from(["sources.gyro", "sources.camera", "sim", "calibration", "deblur", "publish",
                            "pipeline", "logging", "sources", "other"])


@st.composite
def toml_documents(draw) -> bytes:
    lines = []
    for section in draw(st.lists(sections, max_size=6, unique=True)):
        lines.append(f"[{section}]")
        for k, v in draw(st.dictionaries(keys, values, max_size=5)).items():
            lines.append(f"{_toml_str(k)} = {toml_value(v)}")
    return "\n".join(lines).encode()


@st.composite
def mutated(draw) -> bytes:
    data = bytearray(SHIPPED[draw(st.sampled_from(sorted(SHIPPED)))])
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(data)))
        op = draw(st.sampled_from(["flip", "insert", "cut"]))
        if op == "flip" and i < len(data):
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        else:
            del data[i:i + draw(st.integers(1, 40))]
    return bytes(data)


# ------------------------------------------------------------------------------ targets
@FUZZ
@given(st.binary(max_size=400))
def test_random_bytes(data):
    only_config_error(load_bytes, data)


@FUZZ
@given(mutated())
def test_mutated_shipped_configs(data):
    only_config_error(load_bytes, data)


@FUZZ
@given(toml_documents())
def test_random_toml_documents(data):
    only_config_error(load_bytes, data)


def _set(raw: dict, dotted: str, value) -> None:
    *parents, last = dotted.split(".")
    for p in parents:
        raw = raw.setdefault(p, {})
    raw[last] = value


def _every_key() -> list[str]:
    """Every key the parser takes, from the settings' dataclasses (a field added to a section is fuzzed
    without anyone remembering to list it here), plus tables and keys in the wrong place."""
    toml_name = {"lam": "lambda"}
    sections = {"calibration": Calibration, "deblur": config.DeblurConfig, "publish": config.PublishConfig,
                "pipeline": config.PipelineConfig, "sim": config.SimConfig, "rtsp": config.RtspConfig,
                "logging": config.LoggingConfig, "sources.gyro": config.SourceConfig,
                "sources.camera": config.SourceConfig}
    keys = [f"{sec}.{toml_name.get(f.name, f.name)}" for sec, cls in sections.items()
            for f in dataclasses.fields(cls) if f.name not in ("extra", "options")]
    return sorted(set(keys)) + ["sources.gyro.path", "sources.camera.path", "logging", "sources",
                                "radiometry"]


SIM_KEYS = _every_key()


@settings(FUZZ, max_examples=8 * len(SIM_KEYS))        # every key several values
@given(st.sampled_from(SIM_KEYS), values)
def test_one_key_of_a_valid_config_set_to_anything(dotted, value):
    raw = toml_tables.loads(SHIPPED["sim.toml"], NAME)
    try:
        _set(raw, dotted, value)
    except AttributeError:
        return                                    # the path runs through a non-table: parse sees that
    only_config_error(config.parse, raw, NAME)


numbers = (st.floats(allow_nan=True, allow_infinity=True) | st.integers(-10**6, 10**6)
           | st.sampled_from([0, 1e300, -1e-300, 5e-324, 2000]))
motion_specs = st.builds(lambda name, args: name + "".join(f":{a!r}" for a in args),
                         st.sampled_from(["sway", "static", "shake", "vibration", "multirotor", "pan", "slew",
                                          "zzz", ""]), st.lists(numbers, max_size=3)) | st.text(max_size=12)


@FUZZ
@given(motion_specs, st.sampled_from([0.2, 2.0, 120.0]))
def test_an_accepted_sim_motion_is_one_the_payload_can_play(spec, loop_s):
    """Whatever [sim] motion parse accepts loops and stays finite and within the simulated gyro's
    range (a huge one used to be accepted, then pre-rendered for hours at the start)."""
    from thermod.runtime.sources import SIM_GYRO_FULL_SCALE_DPS
    from thermod.sim import playback

    raw = toml_tables.loads(SHIPPED["sim.toml"], NAME)
    raw["sim"].update(motion=spec, loop_s=loop_s, scene="bars")
    try:
        cfg = config.parse(raw, NAME)
    except ConfigError as e:
        assert str(e).startswith(f"{NAME}: sim.motion: expected "), str(e)
        return
    m = playback.loop_motion(cfg.sim.motion, loop_s, cfg.sim.seed)
    w = np.degrees(m.omega(np.linspace(0.0, loop_s, 4001)))
    assert np.all(np.isfinite(w)) and np.abs(w).max() <= 1.01 * SIM_GYRO_FULL_SCALE_DPS, spec


def test_the_fuzzers_reach_valid_and_invalid_configs():
    """The harness itself: the shipped files load through it, and a mutation is caught as ConfigError."""
    assert load_bytes(SHIPPED["sim.toml"]).uses_sim
    with pytest.raises(ConfigError):
        load_bytes(SHIPPED["sim.toml"].replace(b"tau_s = 0.008", b"tau_s = \xff"))
    doc = b"[deblur]\n" + f"{_toml_str('lambda')} = {toml_value([1, {'a': dt.time(1, 2)}])}".encode()
    assert toml_tables.loads(doc)["deblur"]["lambda"] == [1, {"a": dt.time(1, 2)}]
