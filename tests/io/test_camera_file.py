"""CAMERA.toml (thermod.io.camera_file): the presets, every bad key named at once, and any table
either a Calibration or one ConfigError."""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from thermod.errors import ConfigError
from thermod.io import camera_file
from thermod.io.toml_tables import loads
from thermod.physics.calibration import Calibration

# preset → (width, height, horizontal field of view of the pinhole the file describes, in degrees)
PRESETS = {"boson640_14mm": (640, 512, 30.7), "boson640_8.7mm": (640, 512, 47.6),
           "tau2_640_13mm": (640, 512, 45.4), "dji_h20t": (640, 512, 31.8), "dji_h30t": (1280, 1024, 35.5)}


def test_presets_load_with_their_stated_geometry():
    assert sorted(camera_file.preset_names()) == sorted(PRESETS)
    for name, (w, h, hfov) in PRESETS.items():
        c = camera_file.load_camera(camera_file.preset_path(name))
        assert (c.width, c.height) == (w, h)
        assert math.degrees(2 * math.atan(c.width / 2 / c.fx)) == pytest.approx(hfov, abs=0.05)
        assert c.tau_s > 0 and c.frame_rate_hz in (30.0, 60.0)
    with pytest.raises(ConfigError, match="unknown; the presets are"):
        camera_file.preset_path("flir_nonexistent")


def test_field_of_view_focal_length_or_fx_give_the_same_camera(tmp_path):
    base = "[camera]\nwidth = 640\nheight = 512\nframe_rate_hz = 30.0\ntau_s = 0.01\n"
    f = 0.5 * 640 / math.tan(math.radians(50) / 2)
    cams = []
    for extra in ("hfov_deg = 50.0", f"fx = {f}", f"focal_length_mm = {f * 12e-3}\npixel_pitch_um = 12.0"):
        p = tmp_path / "cam.toml"
        p.write_text(base + extra + "\n")
        cams.append(camera_file.load_camera(p))
    assert all(c.fx == pytest.approx(f) and c.fy == c.fx for c in cams)
    assert cams[0].cx == 319.5 and cams[0].cy == 255.5


def test_every_bad_key_is_named_in_one_error(tmp_path):
    p = tmp_path / "cam.toml"
    p.write_text("[camera]\nwidth = 0\nheight = 512\nfocal_length_mm = 14.0\nframe_rate_hz = -1\n"
                 "tau = 0.01\n")
    with pytest.raises(ConfigError) as e:
        camera_file.load_camera(p)
    msg = str(e.value)
    for part in ("cam.toml", "camera.width", "camera.pixel_pitch_um", "camera.frame_rate_hz", "camera.tau_s",
                 "did you mean camera.tau_s"):
        assert part in msg, msg
    p.write_text("[camera]\nwidth = 640\nheight = 512\nhfov_deg = 40\nfx = 800.0\nframe_rate_hz = 30\n"
                 "tau_s = 0.01\nreadout_s = 0.05\n")
    with pytest.raises(ConfigError, match="exactly one of hfov_deg, focal_length_mm, fx"):
        camera_file.load_camera(p)
    p.write_text("[other]\nx = 1\n")
    with pytest.raises(ConfigError, match=r"cam\.toml: expected a \[camera\] table"):
        camera_file.load_camera(p)


VALUES = st.one_of(st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
                   st.text(max_size=5), st.lists(st.integers(), max_size=3))
KEYS = st.sampled_from(["width", "height", "hfov_deg", "fx", "focal_length_mm", "pixel_pitch_um", "cx", "cy",
                        "frame_rate_hz", "tau_s", "readout_s", "f_number", "wavelength_um", "other"])


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(KEYS, VALUES, max_size=10))
def test_any_camera_table_is_a_calibration_or_one_config_error(table):
    try:
        c = camera_file.camera_from_table("fuzz.toml", table)
    except ConfigError as e:
        assert str(e).startswith("fuzz.toml")
    else:
        assert isinstance(c, Calibration) and c.fx > 0 and c.tau_s > 0


def test_loads_rejects_non_toml_as_a_config_error():
    with pytest.raises(ConfigError, match="cam.toml"):
        loads(b"[camera\nwidth=", "cam.toml")
