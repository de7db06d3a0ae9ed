import numpy as np
import pytest

from thermod.physics.calibration import Calibration
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
