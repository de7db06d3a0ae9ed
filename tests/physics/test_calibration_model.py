import numpy as np
import pytest

from thermod.errors import ThermodError
from thermod.physics.calibration import Calibration, CalibrationError
from thermod.physics.detector import iir_alpha, photon_average, thermal_response, thermal_weights
from thermod.physics.geometry import so3_exp


def test_psf_sigma_matches_design_example():
    c = Calibration(wavelength_um=10.0, f_number=1.0, psf_beta=0.6, pixel_pitch_um=17.0)
    assert c.psf_sigma_um == pytest.approx(7.5)
    assert c.psf_sigma_px == pytest.approx(7.5 / 17.0)
    assert c.with_psf_sigma_px(1.2).psf_sigma_px == pytest.approx(1.2)


def test_gyro_to_camera_applies_bias_scale_rotation_offset():
    R = so3_exp([0, 0, np.pi / 2])
    c = Calibration(R_cam_gyro=R, bias_rad_s=(0.1, 0, 0), scale=(2.0, 2.0, 2.0), time_offset_s=0.004)
    t, w = c.gyro_to_camera(np.array([1.0]), np.array([[0.6, 0.0, 0.0]]))
    assert t[0] == pytest.approx(1.004)
    assert np.allclose(w[0], [0.0, 1.0, 0.0], atol=1e-12)  # (0.6−0.1)·2 about gyro x → camera y


def test_camera_to_gyro_inverts_gyro_to_camera():
    c = Calibration(bias_rad_s=(0.01, -0.02, 0.005), scale=(1.02, 0.97, 1.1))
    c = c.with_misalignment([0.02, -0.01, 0.3])
    w_cam = np.random.default_rng(0).normal(size=(7, 3))
    _, back = c.gyro_to_camera(np.zeros(7), c.camera_to_gyro(w_cam))
    assert np.allclose(back, w_cam, atol=1e-12)
    assert c.camera_to_gyro(w_cam[0]).shape == (3,)


def test_attrs_roundtrip():
    c = Calibration(readout_s=0.01, scale=(1.0, 1.01, 0.99), bias_rad_s=(1e-3, 2e-3, 3e-3)).with_misalignment(
        [0.01, 0.0, -0.02])
    back = Calibration.from_attrs(c.camera_attrs(), c.gyro_attrs())
    assert back == c
    assert Calibration.from_dict(c.as_dict()) == c


def test_from_attrs_rejects_bad_shapes():
    with pytest.raises(ValueError, match="R_cam_gyro"):
        Calibration.from_attrs({}, {"R_cam_gyro": np.eye(2)})
    with pytest.raises(ValueError, match="bias_rad_s"):
        Calibration.from_attrs({}, {"bias_rad_s": [1, 2]})


def test_iir_alpha_forms():
    assert iir_alpha(0.001, 0.008, exact=False) == pytest.approx(0.001 / 0.009)
    assert iir_alpha(0.001, 0.008) == pytest.approx(1 - np.exp(-0.125))
    # for h ≪ τ both agree
    assert iir_alpha(1e-6, 0.008) == pytest.approx(iir_alpha(1e-6, 0.008, exact=False), rel=1e-3)


def test_thermal_response_step_follows_exponential():
    h, tau = 0.0005, 0.008
    views = np.ones((200, 1), dtype=np.float32)
    out = thermal_response(views, h, tau, initial=np.zeros(1, np.float32))
    t = h * np.arange(1, 201)
    assert np.allclose(out[:, 0], 1 - np.exp(-t / tau), atol=1e-5)
    assert out.dtype == np.float32


def test_thermal_weights_and_photon_average():
    w = thermal_weights(np.array([0.0, 0.008]), 0.008)
    assert w.sum() == pytest.approx(1.0)
    assert w[1] / w[0] == pytest.approx(np.exp(-1))
    assert photon_average(np.array([[0.0], [2.0]]))[0] == pytest.approx(1.0)


@pytest.mark.parametrize("change, field, expected", [
    ({"R_cam_gyro": np.zeros((3, 3))}, "R_cam_gyro", "rotation matrix"),
    ({"R_cam_gyro": np.diag([1.0, 1.0, -1.0])}, "R_cam_gyro", "det +1"),        # a reflection
    ({"R_cam_gyro": np.eye(3) * 1.01}, "R_cam_gyro", "orthonormal"),
    ({"R_cam_gyro": np.eye(2)}, "R_cam_gyro", "3×3"),
    ({"scale": (1.0, 0.0, 1.0)}, "scale", "(0, 100]"),
    ({"scale": (1e300,)}, "scale", "(0, 100]"),            # overflowed the kernel's size
    ({"scale": (1.0, 1.0)}, "scale", "1 or 3"),
    ({"bias_rad_s": (0.0, float("nan"), 0.0)}, "bias_rad_s", "finite"),
    # beyond any gyro's full scale: the kernel renderer spent 27 s on 1e300, then a numpy ValueError
    ({"bias_rad_s": (1e300, 0.0, 0.0)}, "bias_rad_s", "within ±174.5 rad/s"),
    ({"bias_rad_s": (0.0, 0.0, -175.0)}, "bias_rad_s", "within ±174.5 rad/s"),
    ({"fx": 0.0}, "fx", "positive"),
    ({"fy": -5.0}, "fy", "positive"),
    ({"fx": 1e9}, "fx", "field of view"),           # 640 px over 4e-5°: not a camera
    ({"fy": 1.0}, "fy", "field of view"),           # 480 px over 180°: not a pinhole
    ({"width": 64.7}, "width", "integer"),          # never truncated
    ({"height": 0}, "height", "integer in [1,"),
    ({"width": True}, "width", "number"),
    ({"frame_rate_hz": 0.0}, "frame_rate_hz", "(0, 10000] Hz"),
    ({"rate_hz": float("inf")}, "rate_hz", "finite"),
    ({"pixel_pitch_um": 0.0}, "pixel_pitch_um", "(0, 1000] µm"),
    ({"psf_beta": 0.0}, "psf_beta", "(0, 1]"),
    ({"psf_beta": 1.5}, "psf_beta", "(0, 1]"),
    ({"tau_s": 0.0}, "tau_s", "[1e-06, 1] s"),
    ({"tau_s": "8ms"}, "tau_s", "number"),
    # positive but no detector's: a byte flipped in a file's exponent (found by the recording fuzzer)
    ({"tau_s": 2.848e-306}, "tau_s", "[1e-06, 1] s"),
    ({"tau_s": 2.0}, "tau_s", "[1e-06, 1] s"),
    # an optical PSF the kernel allocation cannot hold (Eq. 19's σ in px, from four fields)
    ({"wavelength_um": 100.0, "f_number": 100.0}, "psf", "σ ≤ 64 px"),
    ({"psf_beta": 1e-3}, "psf", "psf_beta=0.001"),
    ({"wavelength_um": 1e9}, "wavelength_um", "[0.1, 100] µm"),
    ({"time_offset_s": float("nan")}, "time_offset_s", "finite"),
    ({"readout_s": -0.001}, "readout_s", "frame"),
    ({"readout_s": 0.03}, "readout_s", "0.02"),     # longer than the 50 Hz frame period
    ({"cx": float("inf")}, "cx", "finite"),
])
def test_invalid_calibration_cannot_be_built(change, field, expected):
    with pytest.raises(CalibrationError) as e:
        Calibration(**change)
    assert e.value.field == field and str(e.value).startswith(f"{field}: ") and expected in str(e.value)
    assert isinstance(e.value, ThermodError)
    with pytest.raises(CalibrationError):       # every way of making one checks the same
        Calibration().replace(**change)


def test_valid_values_are_normalised_not_rejected():
    c = Calibration(width=np.int64(64), height=48.0, fx=np.float32(100.0), cx=31.5, cy=23.5,
                    R_cam_gyro=np.eye(3).ravel(), scale=[1.02], bias_rad_s=np.zeros(3))
    assert (c.width, c.height) == (64, 48) and type(c.width) is int and type(c.fx) is float
    assert c.scale == (1.02, 1.02, 1.02) and c.R_cam_gyro[1] == (0.0, 1.0, 0.0)
    assert c == Calibration(width=64, height=48, fx=100.0, cx=31.5, cy=23.5, scale=(1.02,) * 3)
    hash(c)                                       # still usable as a key
    # a rotation printed to six decimals is accepted
    R = np.round(so3_exp([0.1, -0.2, 0.3]), 6)
    assert np.allclose(Calibration(R_cam_gyro=R).R_cam_gyro_matrix, R)


def test_with_psf_sigma_px_refuses_sharper_than_diffraction():
    c = Calibration()                               # λ 10 µm, F/1, 17 µm: β = 1 gives 0.265 px
    limit = 0.45 * 10.0 / 17.0
    assert c.with_psf_sigma_px(limit).psf_beta == pytest.approx(1.0)
    for bad in (0.0, -1.0, 0.5 * limit, float("nan")):
        with pytest.raises(CalibrationError, match="psf_sigma_px"):
            c.with_psf_sigma_px(bad)


def test_from_attrs_names_the_attribute():
    with pytest.raises(CalibrationError, match="width: expected an integer") as e:
        Calibration.from_attrs({"width": np.float64(64.7)})
    assert e.value.field == "width"
    with pytest.raises(CalibrationError, match="fx: expected a number, got 'abc'"):
        Calibration.from_attrs({"fx": "abc"})
    with pytest.raises(CalibrationError, match="fx: expected a number"):
        Calibration.from_attrs({"fx": np.array([1.0, 2.0])})
    c = Calibration.from_attrs({"width": np.array([320]), "height": np.int32(240), "cx": 159.5, "cy": 119.5})
    assert (c.width, c.height) == (320, 240)


def test_config_file_gets_the_same_check_with_its_name(tmp_path):
    from thermod.errors import ConfigError
    from thermod.io.calibration_file import load_calibration

    p = tmp_path / "model.toml"
    p.write_text("[calibration]\nfx = 1e9\n")      # in range for the key alone, not for the camera
    with pytest.raises(ConfigError, match=rf"{p}: calibration\.fx: expected a focal length"):
        load_calibration(p)


def test_a_bias_at_the_bound_is_a_kernel_error_not_a_crash(tmp_path):
    """At the largest bias a calibration may hold the renderer refuses the window at once, by name;
    a file beyond it names its key."""
    from thermod.errors import ConfigError
    from thermod.io.calibration_file import load_calibration
    from thermod.physics.calibration import MAX_GYRO_RANGE_RAD_S
    from thermod.physics.kernels.render import render_kernel_grid
    from thermod.physics.kernels.types import KernelError

    c = Calibration(bias_rad_s=(MAX_GYRO_RANGE_RAD_S, 0.0, -MAX_GYRO_RANGE_RAD_S))
    t = np.arange(0.0, 0.2, 0.001)
    with pytest.raises(KernelError, match="gyro"):
        render_kernel_grid(t, np.zeros((t.size, 3)), c, 0.1, grid=(2, 2))
    p = tmp_path / "model.toml"
    p.write_text("[calibration]\nbias_rad_s = [1e300, 0.0, 0.0]\n")
    with pytest.raises(ConfigError, match=rf"^{p}: calibration\.bias_rad_s: expected 3 numbers within"):
        load_calibration(p)
