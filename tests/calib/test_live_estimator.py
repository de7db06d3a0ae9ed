"""thermod.calib.live on its own: the registration's sign and sub-pixel shift on a known translation,
the comet tail taken out of the phase, the bias/offset fit on a simulated recording with known truth
(160×120, the simulator's fine-time thermal renderer), and τ from the tails' shape where the simulated
camera's τ differs from the one in force."""

import dataclasses

import numpy as np
import pytest

from thermod.calib.live import (
    TAU_REF,
    TAU_SCAN,
    GyroIntegral,
    LiveEstimator,
    Pair,
    Registrar,
    predict,
    tail_spectra,
    tail_velocity,
)
from thermod.physics.calibration import Calibration
from thermod.sim.synth import simulate

CAL = Calibration(width=160, height=120, fx=366.0, fy=366.0, cx=79.5, cy=59.5)


def _texture(h=120, w=160, seed=0):
    rng = np.random.default_rng(seed)
    f = np.fft.fft2(rng.standard_normal((h, w)))
    fy, fx = np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]
    return 1000 + 200 * np.real(np.fft.ifft2(f / (0.02 + np.hypot(fx, fy)) ** 1.2)) / 50


def _shifted(img, dx, dy):
    """img moved by (dx, dy) px: the content at p is at p + d (Fourier shift, sub-pixel)."""
    h, w = img.shape
    fy, fx = np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (fx * dx + fy * dy))))


def test_registration_measures_a_known_shift_in_every_patch():
    reg = Registrar(CAL, width=160)
    a = _texture()
    b = _shifted(a, 2.3, -1.6)
    shift, resp = reg.measure(reg.downsample(a), reg.downsample(b))
    assert np.all(resp > 0.3)
    np.testing.assert_allclose(shift, np.tile([2.3, -1.6], (len(shift), 1)), atol=0.15)
    # placed where a prediction says: the same answer from a patch already moved by it
    shift2, _ = reg.measure(reg.downsample(a), reg.downsample(b), predicted=np.tile([2.0, -2.0], (4, 1)))
    np.testing.assert_allclose(shift2, shift, atol=0.15)


@pytest.fixture(scope="module")
def recording():
    truth = {"time_offset": 0.004, "gyro_bias": (0.012, -0.008, 0.0)}
    return simulate("real:1", "multirotor:60", 2.5, CAL, effects=truth, seed=1), truth


def _window(rec, calib, tau_phase=True, tau=False):
    """The recording's consecutive pairs registered as the monitor does (with τ measured on the patch
    pairs whose tails differ when `tau`)."""
    reg = Registrar(calib, width=160)
    integ = GyroIntegral(calib, rec.gyro_t, rec.gyro_rate)
    est = LiveEstimator(4.0)
    b0 = np.asarray(calib.bias_rad_s, float)
    o = calib.time_offset_s
    taus = calib.tau_s * TAU_SCAN
    tails = [None] * len(rec.t)
    for k in range(1, len(rec.t)):
        ta, tb = np.full(4, rec.t[k - 1]), np.full(4, rec.t[k])
        pred = predict(calib, integ, ta, tb, reg.centres, b0, o)
        va = tail_velocity(calib, integ, ta, reg.centres, b0, o) if tau_phase else None
        vb = tail_velocity(calib, integ, tb, reg.centres, b0, o) if tau_phase else None
        a, b = reg.downsample(rec.frames[k - 1]), reg.downsample(rec.frames[k])
        shift, resp = reg.measure(a, b, pred, va, vb, calib.tau_s)
        coherence = None
        if tau:
            for j in (k - 1, k):
                if tails[j] is None:
                    tails[j] = tail_spectra(calib, integ, rec.t[j], reg.centres, b0, o, taus, reg.ext_f_full,
                                            TAU_REF)
            patches = reg.tau_patches(va, vb, calib.tau_s)
            coherence = reg.tau_coherence(a, b, pred, shift, resp, tails[k - 1], tails[k], patches)
        est.add(Pair(rec.t[k - 1], rec.t[k], reg.centres, shift, resp, taus, coherence))
    return est, integ


def test_fit_recovers_the_hidden_bias_and_offset(recording):
    rec, truth = recording
    calib = rec.calibration                         # the nominal one: no bias, no offset
    assert calib.time_offset_s == 0 and not any(calib.bias_rad_s)
    est, integ = _window(rec, calib)
    e = est.fit(calib, integ)
    assert e is not None
    assert abs(e.time_offset_s - truth["time_offset"]) < 0.001, e.as_dict()
    assert e.time_offset_s - truth["time_offset"] < 3 * e.time_offset_sigma + 1e-4
    np.testing.assert_allclose(e.bias_rad_s[:2], truth["gyro_bias"][:2], atol=0.003)
    assert np.all(np.abs(e.bias_rad_s - truth["gyro_bias"]) < 4 * e.bias_sigma + 0.001)
    # the estimate explains the motion better than the nominal calibration, and says so
    assert e.residual_px < e.residual_applied_px
    assert est.residual(calib, integ, e.bias_rad_s, e.time_offset_s) == pytest.approx(e.residual_px)
    assert e.as_dict()["tau_s"] is None and "not estimated" in e.notes[0]     # no pair measured τ


def test_without_the_tail_phase_the_offset_is_biased(recording):
    """Why the comet tail is taken out: the whitened correlation of two comet tails is delayed by a
    speed-dependent fraction of τ, neither the read instant nor the tail's centroid, and the offset
    comes out milliseconds off."""
    rec, truth = recording
    est, integ = _window(rec, rec.calibration, tau_phase=False)
    biased = abs(est.fit(rec.calibration, integ).time_offset_s - truth["time_offset"])
    est, integ = _window(rec, rec.calibration)
    right = abs(est.fit(rec.calibration, integ).time_offset_s - truth["time_offset"])
    # how far off depends on the scene's contrast (real or procedural), the ratio does not
    assert biased > 0.001 and biased > 2 * right, (biased, right)


def test_a_bias_a_smooth_slew_cannot_tell_from_a_delay_is_called_ambiguous(recording):
    """Over one smooth yaw slew the rate's change is nearly the same in every pair, so a yaw bias and
    a delay move the image alike: the fit says so (ρ −0.99 measured) and reports a σ that covers both,
    rather than a confident pair; the multirotor's varied motion separates them."""
    rec = simulate("real:1", "slew:60:yaw:2.5:0", 2.5, CAL,
                   effects={"time_offset": 0.004, "gyro_bias": (0.012, -0.008, 0.0)}, seed=1)
    est, integ = _window(rec, rec.calibration)
    e = est.fit(rec.calibration, integ)
    assert e.ambiguous and abs(e.bias_offset_correlation[1]) > 0.95, e.as_dict()
    assert any(n.startswith("ambiguous: gyro_bias[y] | time_offset") for n in e.notes), e.notes
    assert e.as_dict()["ambiguous"] is True and e.time_offset_sigma > 0.005
    rec, _ = recording
    est, integ = _window(rec, rec.calibration)
    e = est.fit(rec.calibration, integ)
    assert not e.ambiguous and np.all(np.abs(e.bias_offset_correlation) < 0.9), e.as_dict()


def test_too_few_pairs_give_no_estimate(recording):
    rec, _ = recording
    est = LiveEstimator(4.0)
    integ = GyroIntegral(rec.calibration, rec.gyro_t, rec.gyro_rate)
    assert est.fit(rec.calibration, integ) is None


def test_an_offset_far_from_the_one_in_force_is_found():
    """30 ms off (an unstamped USB camera): beyond Gauss–Newton's reach from the offset in force, found
    by the coarse lag search first."""
    rec = simulate("real:1", "multirotor:60", 2.5, CAL, effects={"time_offset": -0.03}, seed=4)
    est, integ = _window(rec, rec.calibration)
    e = est.fit(rec.calibration, integ)
    assert abs(e.time_offset_s + 0.03) < 0.002, e.as_dict()


def test_tail_spectra_of_a_steady_pan_are_the_exponential_transfer():
    """A steady pan: every tail is the exponential of Eq. 10 along one velocity v, whose transfer
    1/(1 − i2πf·vτ) has the phase arctan(2πf·vτ) and whose centroid lags vτ behind the read instant."""
    t = np.arange(0.0, 0.4, 0.001)
    integ = GyroIntegral(CAL, t, np.tile([0.3, 0.8, 0.0], (len(t), 1)))
    reg = Registrar(CAL, width=160)
    taus = CAL.tau_s * TAU_SCAN
    sp = tail_spectra(CAL, integ, 0.3, reg.centres, np.zeros(3), 0.0, taus, reg.ext_f_full, TAU_REF)
    for k in (0, TAU_REF, len(taus) - 1):
        v = tail_velocity(CAL.replace(tau_s=taus[k]), integ, np.full(4, 0.3), reg.centres, np.zeros(3), 0.0)
        assert np.all(np.linalg.norm(v * taus[k], axis=1) > 1.0)               # tails of pixels, not less
        expected = np.arctan(2 * np.pi * (v * taus[k]) @ reg.ext_f_full.T)     # [P, F]
        np.testing.assert_allclose(sp.phase[:, k], expected, atol=0.02)
        np.testing.assert_allclose(sp.centroid[:, k], v * taus[k], rtol=0.01)


@pytest.fixture(scope="module")
def tau_recording():
    """The camera's τ is 10 ms, the calibration in force says 8 ms."""
    return simulate("real:1", "multirotor:60", 2.5, CAL, effects={"time_constant": 0.010}, seed=2)


def test_tau_is_found_where_the_camera_differs_from_the_calibration(tau_recording):
    rec = tau_recording
    calib = rec.calibration
    assert calib.tau_s == pytest.approx(0.008)
    est, integ = _window(rec, calib, tau=True)
    e = est.fit(calib, integ)
    assert e is not None and e.tau_s is not None, e.notes
    assert 0 < e.tau_sigma < 0.1 * e.tau_s
    assert abs(e.tau_s - 0.010) < 2.5 * e.tau_sigma, (e.tau_s, e.tau_sigma)
    assert abs(e.tau_s - 0.008) > 3 * e.tau_sigma                 # significant against the τ in force
    assert e.n_tau >= 24 and e.as_dict()["tau_s"] == e.tau_s and e.as_dict()["tau_s_sigma"] > 0
    # the tails' phase fits better at the estimate than at the τ in force
    assert est.tau_misfit(calib, e.tau_s) < est.tau_misfit(calib, calib.tau_s)


def test_a_steady_pan_shows_no_tau_and_says_why():
    """Tails that do not change from frame to frame cancel in every pair: no τ, never a guess."""
    rec = simulate("real:1", "pan:40", 1.0, CAL, effects={"time_constant": 0.010}, seed=3)
    est, integ = _window(rec, rec.calibration, tau=True)
    tau, sigma, n, note = est.fit_tau(rec.calibration)
    assert tau is None and sigma is None and n < 24
    assert "too slow or too steady" in note


def test_long_tails_do_not_pull_tau_towards_the_one_in_force():
    """A 4° hand-held shake (1–12 Hz): long, curving tails, where the shift at each τ is searched afresh
    (not carried over from the τ in force's), else τ comes out pulled towards the τ in force."""
    rec = simulate("real:1", "shake:4", 2.5, CAL, effects={"time_constant": 0.010}, seed=1)
    est, _ = _window(rec, rec.calibration, tau=True)
    tau, sigma, n, note = est.fit_tau(rec.calibration)
    assert tau is not None, note
    assert abs(tau - 0.010) < 2 * sigma, (tau, sigma, n)


def test_the_monitor_never_applies_an_ambiguous_window():
    """The monitor's rule (issue 34): a significant, stable estimate is proposed, unless a window says
    its bias and offset are confounded; then nothing is proposed, and the refusal is counted."""
    from thermod.runtime.config import MonitorConfig
    from thermod.runtime.monitor import Monitor

    rec = simulate("real:1", "slew:60:yaw:2.5:0", 2.5, CAL,
                   effects={"time_offset": 0.004, "gyro_bias": (0.012, -0.008, 0.0)}, seed=1)
    est, integ = _window(rec, rec.calibration)
    e = est.fit(rec.calibration, integ)
    mon = Monitor(MonitorConfig(apply=True, stable_windows=3), None, None, lambda: rec.calibration)
    b_now = np.zeros(3)
    assert e.ambiguous
    assert mon._motion_change([e, e, e], e, b_now, 0.0) == (None, None)
    assert mon.counters["proposals_refused_ambiguous"] == 1
    clear = dataclasses.replace(e, ambiguous=False, bias_sigma=e.bias_sigma / 100,
                                bias_sigma_stat=e.bias_sigma_stat / 100,
                                time_offset_sigma=e.time_offset_sigma / 100)
    bias, offset = mon._motion_change([clear] * 3, clear, b_now, 0.0)
    assert bias is not None and offset == pytest.approx(e.time_offset_s)
