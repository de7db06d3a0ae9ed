"""Gyro error model: Allan statistics match the parameters; the raw-sample convention inverts
exactly through Calibration.gyro_to_camera; electronic effects (LSB, range, low-pass, jitter,
drift) do what their datasheet names say."""

import math

import numpy as np
import pytest
from scipy import signal

from thermod.errors import ThermodError
from thermod.physics.calibration import Calibration
from thermod.sim import motion
from thermod.sim.gyro_model import DEG, GyroErrorModel, allan_deviation, flicker_noise


def zero(t):
    return np.zeros((np.size(t), 3))


def static_record(model, seconds, rate_hz, seed=0):
    cal = Calibration(rate_hz=rate_hz)
    return model.sample(zero, 0.0, seconds, cal, np.random.default_rng(seed))


def loglog_slope(taus, adev):
    return np.polyfit(np.log(taus), np.log(adev), 1)[0]


def test_white_noise_allan_slope_and_arw():
    rate = 1000.0
    g = GyroErrorModel(noise_rms_deg_s=0.05)
    s = static_record(g, 400.0, rate)
    taus = np.logspace(-2, 0, 9)
    adev = np.array([allan_deviation(s.rate[:, a] / DEG, 1 / rate, taus) for a in range(3)]).mean(axis=0)
    assert loglog_slope(taus, adev) == pytest.approx(-0.5, abs=0.03)
    # σ(1 s) = N (°/√s) = σ_rate/√f, and ARW in °/√h is 60 N
    n_expected = 0.05 / math.sqrt(rate)
    assert adev[-1] == pytest.approx(n_expected, rel=0.05)
    assert g.arw_deg_rt_h(rate) == pytest.approx(60 * n_expected)
    assert GyroErrorModel.from_arw(g.arw_deg_rt_h(rate), rate).noise_rms_deg_s == pytest.approx(0.05)


def test_bias_instability_allan_floor():
    b = 0.12
    dt = 0.01
    x = flicker_noise(800_000, dt, b * DEG, np.random.default_rng(1), corner_hz=0.1) / DEG
    taus = np.logspace(1.3, 2.5, 7)
    adev = np.array([allan_deviation(x[:, a], dt, taus) for a in range(3)]).mean(axis=0)
    floor = math.sqrt(2 * math.log(2) / math.pi) * b
    assert np.median(adev) == pytest.approx(floor, rel=0.15)
    assert abs(loglog_slope(taus, adev)) < 0.12                     # flat: neither white nor random walk


def test_rate_random_walk_allan_slope():
    k = 0.01                                                        # °/s/√s
    g = GyroErrorModel(rate_random_walk_deg_s_sqrt_s=k, rate_hz=50.0)
    s = static_record(g, 20_000.0, 50.0, seed=2)
    taus = np.logspace(1, 2.7, 6)
    adev = np.array([allan_deviation(s.rate[:, a] / DEG, 1 / 50.0, taus) for a in range(3)]).mean(axis=0)
    assert loglog_slope(taus, adev) == pytest.approx(0.5, abs=0.12)
    assert np.median(adev / np.sqrt(taus / 3)) == pytest.approx(k, rel=0.25)


def test_paper_preset_and_lsb_range():
    g = GyroErrorModel.paper()
    assert (g.noise_rms_deg_s, g.resolution_deg_s, g.range_deg_s, g.bias_instability_deg_s) == (
        0.05, 0.0076, 200.0, 0.12)
    mot = motion.parse("slew:250:roll:0.1:0.2")
    traj = motion.Trajectory(mot, 0.0, -0.1, 0.6)
    s = g.sample(traj.omega, -0.05, 0.5, Calibration(), np.random.default_rng(0))
    lsb = 0.0076 * DEG
    q = s.rate.astype(np.float64) / lsb
    np.testing.assert_allclose(q, np.round(q), atol=2e-3)           # on the LSB grid (float32)
    assert s.rate[:, 2].max() == pytest.approx(200 * DEG, abs=lsb)  # saturated at the range
    assert np.sum(np.abs(s.rate[:, 2] - 200 * DEG) < lsb) > 50
    # below the range the error is the noise: 0.05 °/s RMS plus a slowly drifting bias
    ok = s.omega_true[:, 2] < 150 * DEG
    err = (s.rate[ok, 0] - s.omega_true[ok, 0]) / DEG
    assert np.std(np.diff(err)) / math.sqrt(2) == pytest.approx(0.05, rel=0.12)


@pytest.mark.parametrize("scale", [(1.02,) * 3, (0.98, 1.01, 1.03)])
def test_raw_samples_invert_through_the_true_calibration(scale):
    cal = Calibration(bias_rad_s=(0.01, -0.02, 0.005), scale=scale, time_offset_s=0.0037).with_misalignment(
        (0.02, -0.01, 0.03))
    mot = motion.parse("shake:1", seed=3)
    s = GyroErrorModel().sample(mot.omega, 5.0, 6.0, cal, np.random.default_rng(0))
    t_cam, w_cam = cal.gyro_to_camera(s.t, s.rate)
    np.testing.assert_allclose(t_cam, s.t_true, atol=1e-9)
    np.testing.assert_allclose(w_cam, mot.omega(t_cam), atol=2e-6)
    np.testing.assert_allclose(np.diff(s.t), 1e-3, atol=1e-9)      # stamps on the 1 kHz grid
    assert s.t_true[0] <= 5.0 + 1e-3 and s.t_true[-1] >= 6.0 - 1e-3
    # the nominal (identity) calibration does not
    _, w_nom = Calibration().gyro_to_camera(s.t, s.rate)
    assert np.abs(w_nom - mot.omega(s.t_true)).max() > 0.005


def test_clock_drift_and_jitter():
    ppm = 50.0
    ramp = motion.Slew(peak=1.0, axis=1, ramp_s=100.0, hold_s=0.0, start_s=-50.0)   # ω_y ≈ linear
    g = GyroErrorModel(clock_drift_ppm=ppm)
    s = g.sample(ramp.omega, 0.0, 10.0, Calibration(), np.random.default_rng(0), t_anchor=0.0)
    lag = s.t_true - s.t                                            # camera time − stamp
    slope = np.polyfit(s.t, lag, 1)[0]
    assert slope == pytest.approx(ppm * 1e-6, rel=1e-3)
    assert abs(lag[0]) < 1e-9
    # jitter: the stamp stays on the grid, the instant moves: error = dω/dt × jitter
    jit = 20e-6
    s = GyroErrorModel(jitter_s=jit).sample(ramp.omega, 0.0, 2.0, Calibration(), np.random.default_rng(1))
    np.testing.assert_allclose(np.diff(s.t), 1e-3, atol=1e-9)
    w = ramp.omega(s.t)[:, 1]
    slope_w = np.gradient(w, s.t)
    dev = (s.rate[:, 1] - w) / slope_w
    assert np.std(dev) == pytest.approx(jit, rel=0.1)


def test_lowpass_group_delay():
    fc, f = 100.0, 5.0
    sine = motion.SumOfSines(np.array([[f, f, f]]), np.array([[0.01, 0.0, 0.0]]), np.zeros((1, 3)))
    s = GyroErrorModel(lowpass_hz=fc).sample(sine.omega, 0.0, 2.0, Calibration(), np.random.default_rng(0))
    t, y = s.t, s.rate[:, 0].astype(np.float64)
    A = np.c_[np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)]
    (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
    # input ∝ cos(2πft): a delayed output cos(2πf(t − d)) = cos·cos(2πfd) + sin·sin(2πfd)
    delay = math.atan2(a, b) / (2 * np.pi * f)
    w, h = signal.freqs(*signal.butter(2, 2 * np.pi * fc, analog=True), worN=[2 * np.pi * f])
    expect = -np.angle(h[0]) / (2 * np.pi * f)
    assert expect == pytest.approx(math.sqrt(2) / (2 * math.pi * fc), rel=0.01)
    assert delay == pytest.approx(expect, rel=0.03)
    assert math.hypot(a, b) == pytest.approx(0.01 * 2 * np.pi * f * abs(h[0]), rel=0.01)


def test_bad_parameters_raise():
    with pytest.raises(ThermodError, match="noise_rms_deg_s"):
        GyroErrorModel(noise_rms_deg_s=-1).sample(zero, 0, 1, Calibration(), np.random.default_rng())
    with pytest.raises(ThermodError, match="rate_hz"):
        GyroErrorModel(rate_hz=0).sample(zero, 0, 1, Calibration(), np.random.default_rng())
    with pytest.raises(ThermodError, match="empty span"):
        GyroErrorModel().sample(zero, 1, 1, Calibration(), np.random.default_rng())
