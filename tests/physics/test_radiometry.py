"""Counts → °C (thermod.physics.radiometry): the formulas against an independent computation, their
inverse, domains and validation; the [radiometry] config section; the daemon's `celsius` topic as a
real Subscriber receives it; `thermod deblur --celsius` end to end."""

import math
import threading
import time
import warnings

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.support.endpoints import private_endpoint
from tests.support.losses import losses, rare_losses
from thermod.cli import main
from thermod.errors import ConfigError
from thermod.io import recording, wire
from thermod.physics import radiometry
from thermod.physics.calibration import Calibration
from thermod.physics.radiometry import Linear, Planck, RadiometryError
from thermod.runtime import config

FLIR = dict(R=16556.0, B=1428.0, F=1.0, O=-88.0)   # FLIR-like constants from the issue


def kelvin_by_bisection(S, R, B, F, O):  # noqa: E741
    """Independent of the log formula: solve the forward model S(T) = R / (exp(B/T) − F) + O for T."""
    lo, hi = 1.0, 5000.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if R / math.expm1(B / mid) + O < S:   # F = 1: exp(B/T) − 1; S(T) increases with T
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


# ------------------------------------------------------------------------------ formulas
def test_planck_matches_an_independent_root_finding_and_is_plausible():
    p = Planck(**FLIR)
    counts = np.array([-80.0, -40.0, 0.0, 25.0, 50.0, 100.0, 200.0, 1000.0])
    got = p.to_celsius(counts)
    assert got.dtype == np.float32 and got.shape == counts.shape
    want = np.array([kelvin_by_bisection(s, **FLIR) - 273.15 for s in counts])
    np.testing.assert_allclose(got, want, atol=2e-4)
    # these constants put ~0 counts near freezing and ~100 counts near 45 °C: a monotone, plausible curve
    assert -2.0 < got[2] < 0.0 and 40.0 < got[5] < 50.0
    assert np.all(np.diff(got) > 0)


def test_planck_outside_its_domain_is_nan_without_warnings():
    p = Planck(**FLIR)
    sat = Planck(R=1000.0, B=1400.0, F=0.5, O=0.0)     # F < 1: the curve saturates at S − O = R/(1−F) = 2000
    with warnings.catch_warnings():
        warnings.simplefilter("error")                 # any RuntimeWarning from numpy fails the test
        low = p.to_celsius(np.array([-88.0, -100.0, -1e9]))
        high = sat.to_celsius(np.array([1999.0, 2000.0, 5000.0]))
        inv = p.to_counts(np.array([-273.15, -300.0]))
    assert np.isnan(low).all()
    assert np.isfinite(high[0]) and np.isnan(high[1:]).all()
    assert np.isnan(inv).all()
    assert p.to_celsius(np.uint16(50)).shape == ()
    assert p.to_celsius(np.zeros((2, 3), np.uint16)).shape == (2, 3)


@settings(max_examples=200, deadline=None)
@given(R=st.floats(1e3, 1e6), B=st.floats(500.0, 3000.0), F=st.floats(0.5, 2.0), O=st.floats(-5000.0, 5000.0),
       celsius=st.floats(-60.0, 600.0))
def test_planck_inverse_round_trips_within_a_millikelvin(R, B, F, O, celsius):  # noqa: E741
    p = Planck(R=R, B=B, F=F, O=O)
    s = p.to_counts(celsius)
    if not np.isfinite(s):            # F > 1 and T above B / ln F: no signal gives that temperature
        assert F > 1 and celsius + 273.15 >= B / math.log(F) - 1e-6
        return
    assert abs(float(p.to_kelvin(s)) - (celsius + 273.15)) < 1e-3
    assert abs(float(p.to_celsius(s)) - celsius) < 1e-3


def test_linear_model_and_its_inverse():
    lin = Linear(gain=0.01, offset=-273.15)            # FLIR "temperature linear", 10 mK per count
    got = lin.to_celsius(np.array([27315, 29815, 37315], np.uint16))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, [0.0, 25.0, 100.0], atol=1e-4)
    np.testing.assert_allclose(lin.to_counts([0.0, 25.0]), [27315.0, 29815.0], atol=1e-6)


@pytest.mark.parametrize("cls, kw, field", [
    (Planck, dict(R=0.0, B=1428.0), "R"),
    (Planck, dict(R=1.0, B=-1.0), "B"),
    (Planck, dict(R=1.0, B=1.0, F=-0.1), "F"),
    (Planck, dict(R=1.0, B=1.0, O=float("nan")), "O"),
    (Planck, dict(R="1", B=1.0), "R"),
    (Planck, dict(R=True, B=1.0), "R"),
    (Linear, dict(gain=0.0), "gain"),
    (Linear, dict(gain=1e308), "gain"),              # °C of every count would overflow to inf
    (Linear, dict(gain=0.01, offset=-1e300), "offset"),
    (Linear, dict(gain=1.0, offset=float("inf")), "offset"),
])
def test_models_refuse_bad_constants_naming_the_field(cls, kw, field):
    with pytest.raises(RadiometryError) as e:
        cls(**kw)
    assert e.value.field == field and f"radiometry.{field}" in str(e.value)


def test_mapping_round_trip_and_errors():
    for m in (Planck(**FLIR), Linear(gain=0.04, offset=-273.15)):
        assert radiometry.from_mapping(m.as_dict()) == m
    assert radiometry.from_mapping({"model": "none"}) is None
    assert radiometry.from_mapping({"model": "planck", "R": 5.0, "B": 9.0}) == Planck(R=5.0, B=9.0, F=1, O=0)
    for table, field in [({"model": "planck", "R": 5.0}, "B"),
                         ({"model": "linear", "gain": 1.0, "B": 2.0}, "B"),
                         ({"model": "kelvin"}, "model"), ({"model": "none", "R": 1.0}, "R")]:
        with pytest.raises(RadiometryError) as e:
            radiometry.from_mapping(table)
        assert e.value.field == field


# ------------------------------------------------------------------------------ config
def _toml(tmp_path, body):
    p = tmp_path / "thermod.toml"
    p.write_text(config.default_path().read_text() + "\n" + body)
    return p


def test_config_section(tmp_path):
    assert config.load().radiometry is None
    body = '[radiometry]\nmodel = "planck"\nR = 16556\nB = 1428\nF = 1\nO = -88\n'
    cfg = config.load(_toml(tmp_path, body))
    assert cfg.radiometry == Planck(**FLIR)
    cfg = config.load(_toml(tmp_path, '[radiometry]\nmodel = "linear"\ngain = 0.04\noffset = -273.15\n'))
    assert cfg.radiometry == Linear(0.04, -273.15)
    assert config.load(None, {"radiometry.model": "linear", "radiometry.gain": 0.1}).radiometry == Linear(0.1)


@pytest.mark.parametrize("body, key", [
    ('model = "kelvin"', "radiometry.model"),
    ('model = "planck"\nR = 1', "radiometry.B"),
    ('model = "planck"\nR = 1\nB = 0', "radiometry.B"),
    ('model = "planck"\nR = "x"\nB = 1', "radiometry.R"),
    ('model = "linear"\ngain = 1\nR = 2', "radiometry.R"),
    ('model = "linear"\ngian = 1', "radiometry.gian"),
    ('model = "none"\ngain = 1', "radiometry.gain"),
])
def test_config_errors_name_file_and_key(tmp_path, body, key):
    p = _toml(tmp_path, f"[radiometry]\n{body}\n")
    with pytest.raises(ConfigError) as e:
        config.load(p)
    assert str(e.value).startswith(f"{p}: {key}:"), str(e.value)


def test_celsius_is_a_wire_topic_of_frames():
    arr = np.zeros((2, 3), np.float32)
    head = wire.array_header({"t": 1.0, "published": 1.0, "v": 1, "seq": 0}, arr)
    topic, h, got = wire.decode([b"celsius", wire.encode_header(head), arr.tobytes()])
    assert topic == "celsius" and got.shape == (2, 3) and got.dtype == np.float32
    head = wire.array_header({"t": 1.0, "published": 1.0, "v": 1, "seq": 0}, arr.ravel())
    with pytest.raises(wire.MessageError) as e:
        wire.decode([b"celsius", wire.encode_header(head), arr.tobytes()])
    assert e.value.kind == "shape"


# ------------------------------------------------------------------------------ the daemon
@pytest.mark.slow
@pytest.mark.parametrize("source", ["config", "camera"])
def test_daemon_publishes_celsius_next_to_each_frame(source):
    """With Planck constants from the configuration, or (model = "camera") the ones the camera reports:
    the simulated camera reports its own, as a FLIR camera does over GenICam."""
    from thermod.client.subscriber import Subscriber
    from thermod.runtime.daemon import Daemon
    from thermod.runtime.sdnotify import Notifier
    from thermod.sim.payload import SimCamera

    ep = private_endpoint()
    # the simulated payload's counts are ~17 850 (real scene; 17 200–18 900 procedural): near 25 °C
    consts = dict(R=3.4e5, B=1428.0, F=1.0, O=15000.0) if source == "config" else dict(SimCamera.PLANCK)
    overrides = {"publish.endpoint": ep, "deblur.method": "wiener"}
    if source == "config":
        overrides |= {"radiometry.model": "planck", **{f"radiometry.{k}": v for k, v in consts.items()}}
    else:
        overrides |= {"radiometry.model": "camera"}
    cfg = config.load(None, overrides)
    d = Daemon(cfg, notifier=Notifier(None, env={}), overrides=overrides)
    frames, celsius = {}, {}
    stop = threading.Event()
    d.start()
    try:
        serve = threading.Thread(target=d.serve, args=(stop,), daemon=True)
        serve.start()
        with Subscriber(ep, topics=("frame", "celsius")) as sub:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and len(set(frames) & set(celsius)) < 20:
                m = sub.recv(timeout=0.2)
                if m is not None:
                    topic, header, array = m[:3]
                    (frames if topic == "frame" else celsius)[header["frame_id"]] = (header, np.array(array))
            lost = losses(sub)
        health = d.health()
    finally:
        stop.set()
        d.stop()
    assert health["radiometry"] == {"source": source, "model": {"model": "planck", **consts}}
    both = sorted(set(frames) & set(celsius))
    assert len(both) >= 20, (len(frames), len(celsius))
    assert rare_losses(*lost), lost                       # tests/support/losses.py
    R, B, F, O = (consts[k] for k in "RBFO")  # noqa: E741
    for fid in both:
        fh, img = frames[fid]
        ch, c = celsius[fid]
        assert ch["dtype"] == "<f4" and ch["shape"] == fh["shape"] == [480, 640] and c.dtype == np.float32
        assert ch["deblurred"] == fh["deblurred"] and ch["t"] == fh["t"]
        assert ch["radiometry"] == {"model": "planck", **consts}
        want = B / np.log(R / (img.astype(np.float64) - O) + F) - 273.15
        np.testing.assert_allclose(c, want, atol=1e-4)
    c = celsius[both[0]][1]
    assert np.isfinite(c).all() and 15.0 < np.median(c) < 35.0, np.median(c)


# ------------------------------------------------------------------------------ thermod deblur --celsius
@pytest.fixture(scope="module")
def small_rec(tmp_path_factory):
    from thermod.sim import synth

    calib = Calibration(width=320, height=240, cx=159.5, cy=119.5)
    rec = synth.simulate("texture", "pan:30", seconds=0.06, calib=calib, seed=5, effects={"netd": 0.03},
                         truth=False)
    path = tmp_path_factory.mktemp("rad") / "in.h5"
    recording.write(path, rec)
    return path, rec


def test_deblur_celsius_from_a_model_file(small_rec, tmp_path, capsys):
    src, rec = small_rec
    s0 = float(np.median(rec.frames))
    # a model putting the median count at 25 °C: R from the forward formula
    model = Planck(R=(s0 + 500.0) * math.expm1(1428.0 / 298.15), B=1428.0, F=1.0, O=-500.0)
    toml = tmp_path / "model.toml"
    toml.write_text(f'[radiometry]\nmodel = "planck"\nR = {model.R!r}\nB = 1428.0\nF = 1.0\nO = -500.0\n')
    out = tmp_path / "out.h5"
    rc = main(["deblur", str(src), "-o", str(out), "--uniform", "--method", "wiener", "--celsius",
               "--radiometry", str(toml)])
    assert rc == 0, capsys.readouterr().err
    with h5py.File(out, "r") as f:
        c = f["deblurred/celsius"][()]
        deb = f["deblurred/frames"][()]
        attrs = dict(f["deblurred/celsius"].attrs)
    assert c.dtype == np.float32 and c.shape == rec.frames.shape
    np.testing.assert_array_equal(c, model.to_celsius(deb))
    assert attrs["units"] == "degC" and attrs["model"] == "planck" and attrs["R"] == pytest.approx(model.R)
    assert abs(float(np.median(c)) - 25.0) < 1.0


def test_deblur_celsius_from_the_recordings_attributes(small_rec, tmp_path, capsys):
    src, rec = small_rec
    lin = Linear(gain=0.002, offset=-10.0)
    tagged = tmp_path / "tagged.h5"
    rec.extra_attrs = {**rec.extra_attrs, radiometry.RECORDING_GROUP: lin.as_dict()}
    recording.write(tagged, rec)
    out = tmp_path / "out.h5"
    assert main(["deblur", str(tagged), "-o", str(out), "--uniform", "--method", "wiener", "--celsius"]) == 0
    with h5py.File(out, "r") as f:
        np.testing.assert_array_equal(f["deblurred/celsius"][()], lin.to_celsius(f["deblurred/frames"][()]))
        assert f["deblurred/celsius"].attrs["model"] == "linear"


def test_deblur_celsius_without_a_model_says_what_to_give(small_rec, tmp_path, capsys):
    src, _ = small_rec
    out = tmp_path / "out.h5"
    assert main(["deblur", str(src), "-o", str(out), "--uniform", "--celsius"]) == 2
    err = capsys.readouterr().err
    assert "--celsius needs a radiometric model" in err and "--radiometry" in err
    assert not out.exists() and not out.with_name("out.h5.part").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text('[radiometry]\nmodel = "planck"\nR = 1\n')
    assert main(["deblur", str(src), "-o", str(out), "--celsius", "--radiometry", str(bad)]) == 2
    assert f"{bad}: radiometry.B: missing" in capsys.readouterr().err


def test_sighup_reload_applies_a_new_radiometry_model(tmp_path):
    from thermod.runtime.daemon import Daemon
    from thermod.runtime.sdnotify import Notifier

    p = _toml(tmp_path, '[radiometry]\nmodel = "linear"\ngain = 0.01\noffset = -273.15\n')
    ep = private_endpoint()
    d = Daemon(config.load(p, {"publish.endpoint": ep}), notifier=Notifier(None, env={}),
               overrides={"publish.endpoint": ep})
    assert d.cfg.radiometry == Linear(0.01, -273.15)
    p.write_text(p.read_text().replace("gain = 0.01", "gain = 0.1"))
    assert d.reload() and d.cfg.radiometry == Linear(0.1, -273.15)
    p.write_text(p.read_text().replace("gain = 0.1", "gain = 0"))        # refused: keeps the running model
    assert not d.reload() and d.cfg.radiometry == Linear(0.1, -273.15)
    assert "radiometry.gain" in d.reload_status["error"]


def test_camera_model_needs_a_live_camera(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text('[radiometry]\nmodel = "camera"\n')
    with pytest.raises(ConfigError, match=r"m\.toml: radiometry\.model: 'camera' needs a live camera"):
        config.load_radiometry(p)
    p.write_text('[radiometry]\nmodel = "camera"\nR = 1.0\n')
    with pytest.raises(ConfigError, match=r"m\.toml: .*R"):
        config.load_radiometry(p)


def test_a_camera_without_constants_converts_nothing_and_says_so(small_rec, tmp_path):
    """The replay camera (a real driver) reports no constants: no °C, and health says the model is None."""
    from thermod.runtime.daemon import Daemon
    from thermod.runtime.sdnotify import Notifier

    src, _ = small_rec
    cfg_path = tmp_path / "replay.toml"
    cfg_path.write_text(f"""
[sources.gyro]
kind = "replay"
path = "{src}"
[sources.camera]
kind = "replay"
path = "{src}"
[publish]
endpoint = "{private_endpoint()}"
[radiometry]
model = "camera"
""")
    cfg = config.load(cfg_path)
    d = Daemon(cfg, notifier=Notifier(None, env={}))
    assert d.radiometry() is None
    assert d.health()["radiometry"] == {"source": "camera", "model": None}
