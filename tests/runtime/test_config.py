"""Configuration: the packaged files load, and every kind of mistake is one ConfigError naming the
file, the dotted key and what was expected."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from thermod.errors import ConfigError
from thermod.io import calibration_file
from thermod.physics.calibration import Calibration
from thermod.runtime import config

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"


def _write(tmp_path, text, name="t.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


BASE = """
[sources.gyro]
kind = "sim"
[sources.camera]
kind = "sim"
"""


def test_default_is_the_packaged_sim_toml():
    cfg = config.load()
    assert cfg.path.endswith("sim.toml")
    assert cfg.gyro.kind == "sim" and cfg.camera.kind == "sim" and cfg.uses_sim
    assert isinstance(cfg.calibration, Calibration)
    assert (cfg.calibration.width, cfg.calibration.height) == (640, 480)
    assert cfg.calibration.tau_s == pytest.approx(0.008)
    # the paper's IFOV 0.0391° → fx = 1/IFOV
    assert cfg.calibration.fx == pytest.approx(1.0 / math.radians(0.0391))
    # the packaged default runs the solver's documented defaults (α = 1, the finest grid 6×8)
    d = config.DeblurConfig()
    assert cfg.deblur.method == d.method == "kf" and cfg.deblur.alpha == d.alpha == 1.0
    assert tuple(cfg.deblur.grid) == tuple(d.grid) and cfg.deblur.mode == "adaptive"
    assert cfg.sim.frame_rate_hz == 50.0 and cfg.sim.gyro_rate_hz == 1000.0
    assert cfg.publish.endpoint == "tcp://127.0.0.1:5555"


def test_hardware_examples_parse_and_name_missing_device():
    cfg = config.load(CONFIG_DIR / "a655sc_icm42688_spi.toml", check_devices=False)
    assert cfg.gyro.kind == "icm42688_spi" and cfg.gyro.device == "/dev/spidev0.0"
    assert dict(cfg.gyro.options) == {"speed_hz": 10_000_000, "odr_hz": 1000, "full_scale_dps": 2000,
                                      "own_process": True}
    assert cfg.camera.kind == "aravis" and cfg.camera.device == "FLIR-A655sc"
    R = np.asarray(cfg.calibration.R_cam_gyro)
    np.testing.assert_allclose(R, np.diag([1.0, -1.0, -1.0]))
    assert cfg.deblur.mode == "adaptive" and cfg.deblur.grid == (3, 4)
    boson = config.load(CONFIG_DIR / "boson_serial.toml", check_devices=False)
    assert boson.gyro.kind == "serial" and boson.gyro.options["baud"] == 921600
    assert boson.camera.kind == "v4l2" and boson.calibration.height == 512
    if not Path("/dev/spidev0.0").exists():
        with pytest.raises(ConfigError, match=r"a655sc_icm42688_spi\.toml: sources\.gyro\.device: device "
                                              r"'/dev/spidev0\.0' does not exist"):
            config.load(CONFIG_DIR / "a655sc_icm42688_spi.toml")


def test_frozen_and_values(tmp_path):
    p = _write(tmp_path, BASE + "[deblur]\nlambda = 3000\nmethod = 'wiener'\n[pipeline]\nworkers = 3\n")
    cfg = config.load(p)
    assert cfg.deblur.lam == 3000.0 and isinstance(cfg.deblur.lam, float)
    assert cfg.deblur.method == "wiener" and cfg.pipeline.workers == 3
    with pytest.raises(AttributeError):
        cfg.deblur.lam = 1.0
    with pytest.raises(TypeError):
        cfg.gyro.options["x"] = 1


@pytest.mark.parametrize("extra, message", [
    ("[deblur]\nlambda = -3\n", r"deblur\.lambda: expected a value in \(0\.0, 1000000000\.0\], got -3"),
    ("[deblur]\nlambda = 'big'\n", r"deblur\.lambda: expected a number, got 'big'"),
    ("[deblur]\nmethod = 'richardson'\n",
     r"deblur\.method: expected one of 'kf', 'wiener', got 'richardson'"),
    ("[deblur]\nalpha = 0.5\n", r"deblur\.alpha: expected 1 or 2/3"),
    ("[deblur]\ngrid = [3]\n", r"deblur\.grid: expected an array of 2 integers in \[1, 16\]"),
    ("[deblur]\nlamda = 3\n", r"deblur\.lamda: unknown key"),
    ("[publish]\nhwm = 0\n", r"publish\.hwm: expected a value in \[1, 1000000\], got 0"),
    ("[publish]\nraw = 1\n", r"publish\.raw: expected true or false, got 1"),
    ("[publish]\nendpoint = 'localhost:5555'\n", r"publish\.endpoint: expected a ZeroMQ endpoint"),
    ("[publish]\ncurve_secret_key = '/nonexistent/key'\n",
     r"publish\.curve_secret_key: CURVE key file '/nonexistent/key' does not exist"),
    ("[pipeline]\nworkers = 2.5\n", r"pipeline\.workers: expected an integer, got 2\.5"),
    ("[pipeline]\njob_queue = 0\n", r"pipeline\.job_queue: expected a value in \[1, 64\]"),
    ("[calibration]\ntau_s = 0\n", r"calibration\.tau_s: expected a value in \[1e-06, 1\.0\]"),
    ("[calibration]\nbias_rad_s = [0, 0]\n", r"calibration\.bias_rad_s: expected an array of 3 numbers"),
    ("[calibration]\nR_cam_gyro = [[1,0,0],[0,1,0],[0,0,2]]\n",
     r"calibration\.R_cam_gyro: expected a rotation"),
    ("[calibration]\nR_cam_gyro = [[1,0],[0,1]]\n", r"calibration\.R_cam_gyro: expected a 3×3 array"),
    ("[calibration]\nframe_rate_hz = 60.0\n", r"calibration\.frame_rate_hz/rate_hz: expected to match sim"),
    ("[calibration]\nreadout_s = 0.05\n", r"calibration\.readout_s: expected a value in \[0\.0, 0\.02\]"),
    ("[sim]\ngyro_rate_hz = 1234.0\n", r"sim\.gyro_rate_hz: expected one of"),
    ("[logging]\nlevel = 'loud'\n", r"logging\.level: expected one of"),
    ("[daemon]\nx = 1\n", r"t\.toml: daemon: unknown key"),
])
def test_each_mistake_names_file_and_key(tmp_path, extra, message):
    p = _write(tmp_path, BASE + extra)
    with pytest.raises(ConfigError, match=message) as ei:
        config.load(p)
    assert str(ei.value).startswith(str(p) + ": ")


def test_source_errors(tmp_path):
    p = _write(tmp_path, "[sources.gyro]\nkind = 'gyro9000'\n[sources.camera]\nkind = 'sim'\n")
    with pytest.raises(ConfigError, match=r"sources\.gyro\.kind: expected one of 'sim', 'replay', "):
        config.load(p)
    p = _write(tmp_path, "[sources.camera]\nkind = 'sim'\n")
    with pytest.raises(ConfigError, match=r"sources\.gyro: missing"):
        config.load(p)
    p = _write(tmp_path, "[sources.gyro]\nkind = 'icm42688_spi'\n[sources.camera]\nkind = 'sim'\n")
    with pytest.raises(ConfigError, match=r"sources\.gyro\.device: missing \(expected a string\)"):
        config.load(p)
    p = _write(tmp_path, "[sources.gyro]\nkind = 'icm42688_i2c'\ndevice = '/dev/i2c-77'\naddress = 0x42\n"
                         "[sources.camera]\nkind = 'sim'\n")
    with pytest.raises(ConfigError, match=r"sources\.gyro\.address: expected one of 104, 105, got 66"):
        config.load(p, check_devices=False)
    with pytest.raises(ConfigError, match=r"sources\.gyro\.device: device '/dev/i2c-77' does not exist"):
        _write(tmp_path, "[sources.gyro]\nkind = 'icm42688_i2c'\ndevice = '/dev/i2c-77'\n"
                         "[sources.camera]\nkind = 'sim'\n")
        config.load(tmp_path / "t.toml")
    p = _write(tmp_path, "[sources.gyro]\nkind = 'replay'\npath = 'nothere.h5'\n"
                         "[sources.camera]\nkind = 'sim'\n")
    with pytest.raises(ConfigError, match=r"sources\.gyro\.path: recording '.*nothere\.h5' does not exist"):
        config.load(p)
    # a recording path is relative to the config file
    (tmp_path / "rec.h5").write_bytes(b"")
    p = _write(tmp_path, "[sources.gyro]\nkind = 'replay'\npath = 'rec.h5'\n"
                         "[sources.camera]\nkind = 'replay'\npath = 'rec.h5'\nspeed = 2\n")
    cfg = config.load(p)
    assert cfg.gyro.device == str(tmp_path / "rec.h5") and cfg.camera.options["speed"] == 2.0
    p = _write(tmp_path, "[sources.gyro]\nkind = 'replay'\npath = 'rec.h5'\n"
                         "[sources.camera]\nkind = 'replay'\npath = 'rec.h5'\n[sim]\nseed = 1\n")
    with pytest.raises(ConfigError, match=r"sim: only allowed when a source has kind = 'sim'"):
        config.load(p)


def test_non_table_section():
    raw = {"sources": {"gyro": {"kind": "sim"}, "camera": {"kind": "sim"}}, "deblur": 3}
    with pytest.raises(ConfigError, match=r"^x\.toml: deblur: expected a table, got an integer$"):
        config.parse(raw, "x.toml")


def test_file_level_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.toml: no such configuration file"):
        config.load(tmp_path / "nope.toml")
    p = _write(tmp_path, "[deblur\nmethod=")
    with pytest.raises(ConfigError, match=r"t\.toml: not valid TOML"):
        config.load(p)


def test_overrides_are_validated_like_the_file():
    cfg = config.load(None, {"publish.endpoint": "tcp://127.0.0.1:6001", "deblur.lambda": 2500})
    assert cfg.publish.endpoint == "tcp://127.0.0.1:6001" and cfg.deblur.lam == 2500.0
    with pytest.raises(ConfigError, match=r"^--set deblur\.lambda=x: expected a number, got 'x'$"):
        config.load(None, {"deblur.lambda": "x"})
    assert config.parse_override("deblur.method=wiener") == ("deblur.method", "wiener")
    assert config.parse_override("deblur.grid=[2, 4]") == ("deblur.grid", [2, 4])
    assert config.parse_override("publish.raw=true") == ("publish.raw", True)
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        config.parse_override("deblur.method")


def test_v4l2_telemetry_rows_and_clock_reach_the_driver():
    from thermod.runtime.sources import build_camera

    over = {"sources.camera.telemetry_top": 2, "sources.camera.timestamp_clock": "device"}
    cfg = config.load(CONFIG_DIR / "boson_serial.toml", check_devices=False, overrides=over)
    cam = build_camera(cfg)                   # constructing opens nothing: start() does
    assert (cam.top, cam.bottom, cam.raw_height) == (2, 0, 514)
    assert cam.timestamp_clock == "device"
    with pytest.raises(ConfigError, match="sources.camera.timestamp_clock"):
        config.load(CONFIG_DIR / "boson_serial.toml", check_devices=False,
                    overrides={"sources.camera.timestamp_clock": "wall"})


def test_non_utf8_byte_is_a_config_error_naming_the_line(tmp_path):
    p = tmp_path / "t.toml"
    p.write_bytes(BASE.encode() + b"[deblur]\n# caf\xe9\nmethod = 'kf'\n")
    with pytest.raises(ConfigError, match=r"t\.toml: line 7: expected UTF-8 text, got byte 0xe9"):
        config.load(p)
    with pytest.raises(ConfigError, match=r"t\.toml: line 7: expected UTF-8"):
        calibration_file.load_calibration(p)


def test_calibration_own_checks_become_config_errors_naming_the_file(tmp_path):
    """What Calibration refuses on construction (here a field of view that no lens has: a 1e-3 px focal
    length) reaches the user as a ConfigError naming the file and the key."""
    p = _write(tmp_path, BASE + "[calibration]\nfx = 1e-3\n")
    with pytest.raises(ConfigError, match=r"t\.toml: calibration\.fx: "):
        config.load(p)
    with pytest.raises(ConfigError, match=r"t\.toml: calibration\.fx: "):
        calibration_file.load_calibration(p)


def test_registry_is_the_one_list_of_kinds():
    from thermod.runtime import sources

    assert tuple(sources.GYROS) == ("sim", "replay", "icm42688_spi", "icm42688_i2c", "mpu6000", "bmi088",
                                    "iio", "serial", "video")
    assert tuple(sources.CAMERAS) == ("sim", "replay", "aravis", "v4l2")
    # an option's schema in the registry is what the loader enforces
    lo = sources.GYROS["serial"].options["baud"].lo
    p = {"sources": {"gyro": {"kind": "serial", "device": "/dev/ttyUSB9", "baud": lo - 1},
                     "camera": {"kind": "sim"}}}
    with pytest.raises(ConfigError, match=rf"sources\.gyro\.baud: expected a value in \[{lo}, "):
        config.parse(p, "x.toml", check_devices=False)


def test_daemon_reaches_the_simulator_only_through_the_registry():
    import ast

    src = (Path(__file__).resolve().parents[2] / "thermod/runtime").glob("*.py")
    for f in src:
        if f.name == "sources.py":
            continue
        tree = ast.parse(f.read_text())
        mods = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)] + \
               [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        assert not any(m and m.startswith("thermod.sim") for m in mods), f.name


# ------------------------------------------------------------------------------ SIGHUP reload
@pytest.fixture
def daemon(tmp_path):
    """A daemon on the simulated payload, constructed (sources, rings, pipeline) but not started:
    reload touches only the configuration and the pipeline's settings."""
    from thermod.runtime.daemon import Daemon
    from thermod.runtime.sdnotify import Notifier

    p = tmp_path / "sim.toml"
    p.write_text(config.default_path().read_text())
    d = Daemon(config.load(p), notifier=Notifier(env={}))
    yield d, p


def test_reload_applies_a_good_file(daemon):
    d, p = daemon
    p.write_text(p.read_text().replace("tau_s = 0.008", "tau_s = 0.009"))
    assert d.reload() is True
    assert d.pipeline.calib.tau_s == 0.009 and d.cfg.calibration.tau_s == 0.009
    assert d.health()["reload"]["ok"] is True and d.counters["reloads"] == 1


@pytest.mark.parametrize("damage, why", [
    (lambda b: b.replace(b"tau_s = 0.008", b"tau_s = 0.008 # \xff"), r"expected UTF-8 text, got byte 0xff"),
    (lambda b: b.replace(b"tau_s = 0.008", b"tau_s = -1"), r"calibration\.tau_s: expected a value"),
    (lambda b: b + b"\n[deblur\n", r"not valid TOML"),
    (lambda b: b.replace(b"width = 640", b"width = 320"),
     r"calibration\.width/height: expected the running camera's frame size 640×480, got 320×480"),
    (None, r"no such configuration file"),
    # accepted before: the gyro bias went to the workers (a 27 s kernel render, then a ValueError) ...
    (lambda b: b.replace(b"bias_rad_s = [0.0, 0.0, 0.0]", b"bias_rad_s = [1e300, 0.0, 0.0]"),
     r"calibration\.bias_rad_s: expected 3 numbers within"),
    # ... and a motion the next start could not play
    (lambda b: b.replace(b'motion = "multirotor:60"', b'motion = "zzz"'), r"sim\.motion: expected a looping"),
])
def test_reload_failure_keeps_running_on_the_old_configuration(daemon, damage, why):
    d, p = daemon
    before = d.pipeline.calib, d.pipeline.deblur, d.cfg
    if damage is None:
        p.unlink()
    else:
        p.write_bytes(damage(p.read_bytes()))
    assert d.reload() is False
    assert (d.pipeline.calib, d.pipeline.deblur, d.cfg) == before
    h = d.health()["reload"]
    assert h["ok"] is False and h["at"] is not None
    assert h["error"].startswith(str(p)) and __import__("re").search(why, h["error"]), h["error"]
    assert d.counters["reload_errors"] == 1 and d.counters["reloads"] == 0


def test_reload_survives_an_unexpected_exception(daemon, monkeypatch):
    d, _ = daemon

    def broken(*a, **kw):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(config, "load", broken)
    assert d.reload() is False
    assert d.health()["reload"]["error"] == "RuntimeError: disk on fire"


def test_every_source_class_offers_the_source_protocol():
    """name, clock and stats() are what health reads: each driver class has them, without probing."""
    import importlib

    from thermod.drivers.camera_base import CameraSource
    from thermod.drivers.gyro_base import GyroSource

    classes = [GyroSource, CameraSource]
    for mod, name in [("thermod.drivers.replay", "ReplayGyro"), ("thermod.drivers.replay", "ReplayCamera"),
                      ("thermod.drivers.icm42688", "ICM42688"), ("thermod.drivers.mpu6000", "MPU6000"),
                      ("thermod.drivers.bmi088", "BMI088Gyro"), ("thermod.drivers.iio", "IIOGyro"),
                      ("thermod.drivers.serial_imu", "SerialIMU"),
                      ("thermod.drivers.v4l2_camera", "V4L2Camera"),
                      ("thermod.sim.payload", "SimCamera")]:
        classes.append(getattr(importlib.import_module(mod), name))
    for cls in classes:
        for attr in ("name", "clock", "stats", "start", "stop", "poll"):
            assert hasattr(cls, attr), (cls.__name__, attr)
    from thermod.drivers.replay import ReplayGyro
    assert ReplayGyro.clock is None                       # a replay has no device clock to report


def test_register_gyro_device_names_are_checked_with_file_and_key(tmp_path):
    from thermod.runtime import sources

    p = _write(tmp_path, "[sources.gyro]\nkind = 'icm42688_spi'\ndevice = '/dev/ttyS0'\n"
                         "[sources.camera]\nkind = 'sim'\n")
    cfg = config.load(p, check_devices=False)
    with pytest.raises(ConfigError, match=r"t\.toml: sources\.gyro\.device: expected /dev/spidevB\.C"):
        sources.build_gyro(cfg)
    cfg = config.load(p, {"sources.gyro.kind": "icm42688_i2c"}, check_devices=False)
    with pytest.raises(ConfigError, match=r"t\.toml: sources\.gyro\.device: expected /dev/i2c-N"):
        sources.build_gyro(cfg)


def test_every_problem_is_listed_with_its_source_and_a_suggestion(tmp_path):
    """One ConfigError lists every bad key (not only the first), each line naming where the value came
    from: the file, or the --set that gave it; unknown keys come with the nearest known key."""
    p = _write(tmp_path, BASE + "[deblur]\nlamda = 3\nmethod = 'richardson'\n[pipeline]\nworkers = -1\n"
                              "[publsh]\nhwm = 3\n")
    over = dict([config.parse_override("rtsp.bitrate_kbps=1"), config.parse_override("sim.sed=4")])
    with pytest.raises(ConfigError) as ei:
        config.load(p, over)
    lines = str(ei.value).splitlines()
    f = str(p)
    assert sorted(lines) == sorted([
        f"{f}: deblur.lamda: unknown key (did you mean deblur.lambda?)",
        f"{f}: deblur.method: expected one of 'kf', 'wiener', got 'richardson'",
        f"{f}: pipeline.workers: expected a value in [0, 64], got -1",
        f"{f}: publsh: unknown key (did you mean publish?)",
        "--set rtsp.bitrate_kbps=1: expected a value in [50, 100000], got 1",
        "--set sim.sed=4: unknown key (did you mean sim.seed?)",
    ]), lines


def test_a_bad_override_never_blames_the_file(tmp_path):
    with pytest.raises(ConfigError) as ei:
        config.load(None, dict([config.parse_override("publish.endpoint=localhost:1")]))
    assert str(ei.value).startswith("--set publish.endpoint=localhost:1: expected a ZeroMQ endpoint")
    with pytest.raises(ConfigError, match=r"^--set deblur\.method\.x=1: deblur\.method is not a table"):
        config.load(None, {"deblur.method.x": 1})
    # a relative path given on the command line is relative to the working directory, not the file
    with pytest.raises(ConfigError, match=r"^--set publish\.curve_secret_key=nokey: CURVE key file '"
                                          + str(Path.cwd() / "nokey")):
        config.load(None, {"publish.curve_secret_key": "nokey"})


@pytest.mark.parametrize("given, problem", [
    ({"a..b": 1}, r"^--set a\.\.b=1: expected a dotted key"),
    ({".x": 1}, r"^--set \.x=1: expected a dotted key"),
    ({"deblur.": 1}, r"^--set deblur\.=1: expected a dotted key"),
    ({"deblur.lambda.x": 1}, r"^--set deblur\.lambda\.x=1: expected a number, got \{'x': 1\}$"),
    ({"newtable.key": 1}, r"^--set newtable\.key=1: unknown key$"),
    ({"sim.cache_dir": "a\0b"}, r"^--set sim\.cache_dir='a\\x00b': expected a directory path"),  # not raw
])
def test_an_override_that_is_not_a_key_of_the_file_blames_the_override(given, problem):
    """A key with an empty part, or one that creates a table the file does not have, is the --set's
    problem (it used to name the file: "sim.toml: a: unknown key")."""
    with pytest.raises(ConfigError, match=problem):
        config.load(None, given)
    text = "=".join(f"{k}={v}" for k, v in given.items())
    if ".." in text or text.startswith(".") or ".=" in text:
        with pytest.raises(ConfigError, match=r"^--set '.*': expected KEY=VALUE with KEY a dotted key"):
            config.parse_override(text)


@pytest.mark.parametrize("key, value, problem", [
    ("motion", "zzz", r"sim\.motion: expected a looping motion spec .*unknown motion 'zzz'"),
    ("motion", "pan:50", r"sim\.motion: expected a looping motion spec .*not periodic"),
    ("motion", "sway:2:0", r"sim\.motion: expected a looping motion spec"),
    ("motion", "vibration:10:0", r"sim\.motion: expected a motion within .*not finite"),
    # a hang before: the loop's pre-render runs in proportion to the rate (and ignored SIGTERM)
    ("motion", "multirotor:1e300", r"sim\.motion: expected a motion within the simulated gyro's "
                                   r"±2000 °/s, got 'multirotor:1e300' \(peak [\d.]+e\+300 °/s\)"),
    ("scene", "zzz", r"sim\.scene: expected bars, points, texture, real\[:N\] or an image file: "
                     r"'zzz' does not exist"),
    ("scene", "", r"sim\.scene: expected bars, .* got ''"),
    ("scene", "/dev/null", r"sim\.scene: expected .*a device or special file"),
    ("scene", "a\0b", r"sim\.scene: expected .*NUL character"),
    ("cache_dir", "a\0b", r"sim\.cache_dir: expected a directory path without NUL characters"),
])
def test_a_sim_spec_the_payload_cannot_play_is_refused_at_load(tmp_path, key, value, problem):
    """[sim] scene and motion are checked when the file is read, naming the file and key: they were
    read only at the start, as `thermod sim`'s --scene/--motion (or a ValueError for a NUL)."""
    p = _write(tmp_path, BASE + f"[sim]\n{key} = {json.dumps(value)}\n")
    with pytest.raises(ConfigError) as ei:
        config.load(p)
    msg = str(ei.value)
    assert msg.startswith(f"{p}: sim.{key}: ") and re.search(problem, msg), msg
    assert "--motion" not in msg and "--scene" not in msg and len(msg.splitlines()) == 1
    p.write_text(BASE + "[sim]\nscene = \"bars\"\nmotion = \"multirotor:600\"\n")   # ~1900 °/s: fits
    assert config.load(p).sim.motion == "multirotor:600"


def test_dataclass_defaults_are_the_schema_defaults():
    """Each section's defaults, its TOML schema and an empty table agree: one declaration."""
    from thermod.io.toml_tables import schema_of

    cfg = config.parse({"sources": {"gyro": {"kind": "sim"}, "camera": {"kind": "sim"}}}, "x.toml")
    for name, cls in config._config_sections().items():
        assert getattr(cfg, name) == cls(), name
        schema = schema_of(cls)
        assert schema and all(getattr(cls(), k.attr) == k.default for k in schema.values()), name
    assert cfg.deblur == config.DeblurConfig()
    assert config.PublishConfig().hwm == config.endpoints.DEFAULT_HWM


def test_the_key_reference_is_the_loader_schema():
    """`thermod run --list-keys` prints the schema the loader checks: as a TOML file (with both sources
    set to sim) it loads, and gives exactly the defaults of an empty configuration."""
    import tomllib

    from thermod import cli

    text = config.reference()
    doc = text.replace("kind = ...  #", 'kind = "sim"  #')
    parsed = config.parse(tomllib.loads(doc), "reference.toml")
    assert parsed == config.parse({"sources": {"gyro": {"kind": "sim"}, "camera": {"kind": "sim"}}},
                                  "reference.toml")
    for line in ("hwm = 100  # messages queued per subscriber; a value in [1, 1000000]",
                 "# lambda = ...  # data weight; absent = the solver's; a value in (0.0, 1000000000.0]",
                 '#   timestamp_clock = "auto"  # one of \'auto\', \'monotonic\', \'device\''):
        assert line in text.splitlines(), line
    assert cli.main(["run", "--list-keys"]) == 0
