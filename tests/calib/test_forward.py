"""The fast forward model (thermod.calib.forward): geometry, thermal response, readout, and the simulator."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from thermod.calib.forward import ForwardModel, downsample, orientations, predict_frames
from thermod.physics.calibration import Calibration
from thermod.physics.geometry import integrate_rotations
from thermod.sim import motion as mo
from thermod.sim.synth import simulate, truth_calibration

CAL = Calibration(width=200, height=160, fx=500.0, fy=500.0, cx=99.5, cy=79.5, tau_s=0.008)


def blob(cal=CAL, sigma=1.5, x=None, y=None, amp=1000.0):
    yy, xx = np.mgrid[0:cal.height, 0:cal.width]
    x = cal.cx if x is None else x
    y = cal.cy if y is None else y
    return (100.0 + amp * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2))).astype(np.float32)


def pan_gyro(rate_y: float, t_on: float, t_end: float = 0.4, rate_hz: float = 1000.0):
    t = np.arange(0.0, t_end, 1.0 / rate_hz)
    w = np.zeros((len(t), 3), np.float32)
    w[t >= t_on, 1] = rate_y
    return t, w


def moments(img, background=100.0):
    w = np.clip(img - background, 0, None).astype(np.float64)
    w[w < 1e-5 * w.max()] = 0.0            # float32 rounding of the far background would bias the 2nd moment
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    s = w.sum()
    mx, my = (w * xx).sum() / s, (w * yy).sum() / s
    return mx, my, (w * (xx - mx) ** 2).sum() / s


def test_orientations_follow_integrate_rotations_semantics():
    rng = np.random.default_rng(0)
    t = np.arange(0, 0.3, 0.001)
    w = rng.normal(0, 0.5, (len(t), 3))
    tq = np.sort(rng.uniform(0.05, 0.29, 40))
    Q = orientations(tq, t, w, 0.1)
    merged = np.union1d(t, np.r_[tq, 0.1])
    wm = np.stack([np.interp(merged, t, w[:, a]) for a in range(3)], axis=1)
    Qr = integrate_rotations(merged, wm, 0.1)[np.searchsorted(merged, tq)]
    np.testing.assert_allclose(Q, Qr, atol=1e-12)
    np.testing.assert_allclose(orientations(np.array([0.1]), t, w, 0.1)[0], np.eye(3), atol=1e-15)


def test_no_motion_predicts_the_reference_with_fpn_added_back():
    ref = blob()
    fpn = np.random.default_rng(1).normal(0, 5, ref.shape).astype(np.float32)
    t, w = pan_gyro(0.0, 0.0)
    fm = ForwardModel(ref, np.array([0.2, 0.22]), t, w, CAL, t_ref=0.1, fpn=fpn)
    p, v = fm.predict(CAL)
    assert p.dtype == np.float32 and p.shape == (2, 160, 200)
    assert v.all()
    np.testing.assert_allclose(p, np.broadcast_to(ref, p.shape), atol=1e-2)


def test_steady_pan_trails_the_view_by_tau_with_an_exponential_tail():
    # ω_y > 0 turns the camera right: the scene moves left at v = fx·ω px/s (Eq. 16). After ≫ τ the
    # thermal state is the exponential average (Eq. 11): centroid τ behind, tail variance (vτ)².
    omega = 0.2
    v = CAL.fx * omega                                    # 100 px/s
    t, w = pan_gyro(omega, 0.1)
    t_k = 0.1 + 0.1
    fm = ForwardModel(blob(x=140.0), np.array([t_k]), t, w, CAL, t_ref=0.1, max_step_px=0.1)
    p, _ = fm.predict(CAL)
    mx, my, var = moments(p[0])
    assert mx == pytest.approx(140.0 - v * (t_k - 0.1 - CAL.tau_s), abs=0.05)
    assert my == pytest.approx(CAL.cy, abs=1e-3)
    assert var == pytest.approx(1.5**2 + (v * CAL.tau_s) ** 2, rel=0.05)
    # A longer τ lags more (same cached views, only the IIR changes).
    p2, _ = fm.predict(CAL.replace(tau_s=0.016))
    assert moments(p2[0])[0] == pytest.approx(140.0 - v * (t_k - 0.1 - 0.016), abs=0.05)


@pytest.mark.parametrize("offset", [0.004, -0.004])
def test_time_offset_delays_the_gyro_motion_in_camera_time(offset):
    # t_cam = t_gyro + time_offset_s: a positive offset means the pan the gyro saw at 0.1 s reached
    # the camera at 0.1 + offset, so at t_k the scene (moving left at v) is v·offset px further right.
    omega, t_k = 0.2, 0.2
    v = CAL.fx * omega                                    # 100 px/s: 0.4 px for 4 ms
    t, w = pan_gyro(omega, 0.1)
    fm = ForwardModel(blob(x=140.0), np.array([t_k]), t, w, CAL, t_ref=0.09, max_step_px=0.1)
    x0 = moments(fm.predict(CAL)[0][0])[0]
    x1 = moments(fm.predict(CAL.replace(time_offset_s=offset))[0][0])[0]
    assert x1 - x0 == pytest.approx(v * offset, abs=0.02)


def test_rolling_readout_shears_a_vertical_bar():
    ref = np.full((160, 200), 100.0, np.float32)
    ref[:, 118:122] = 1100.0
    omega = 0.4                                               # 200 px/s
    t, w = pan_gyro(omega, 0.1)
    ro = 0.015
    cal = CAL.replace(readout_s=ro)
    fm = ForwardModel(ref, np.array([0.2]), t, w, cal, t_ref=0.1, max_step_px=0.2)
    p, _ = fm.predict(cal)
    rows = np.arange(10, 150)
    cx = np.array([moments(p[0][r:r + 1])[0] for r in rows])
    slope = np.polyfit(rows, cx, 1)[0]
    # row r is read T_ro·(1 − (r+1)/H) early: lower rows are read later, so moved further left.
    assert slope == pytest.approx(-CAL.fx * omega * ro / 160, rel=0.03)
    p0, _ = fm.predict(CAL)
    assert np.polyfit(rows, [moments(p0[0][r:r + 1])[0] for r in rows], 1)[0] == pytest.approx(0, abs=1e-3)


def test_working_resolution_agrees_with_full_resolution():
    rng = np.random.default_rng(2)
    ref = cv2.GaussianBlur(rng.normal(1000, 50, (160, 200)).astype(np.float32), (0, 0), 2.0)
    t = np.arange(0, 0.4, 0.001)
    w = np.zeros((len(t), 3), np.float32)
    on = t > 0.1
    w[on] = np.c_[0.3 * np.sin(20 * t[on]), 0.4 * np.sin(13 * t[on] + 1), 0.5 * np.sin(9 * t[on])]
    frames_t = np.arange(0.12, 0.4, 0.02)
    full, vf = predict_frames(ref, frames_t, t, w, CAL, t_ref=0.1)
    half, vh = predict_frames(ref, frames_t, t, w, CAL, t_ref=0.1, scale=0.5)
    assert half.shape == (len(frames_t), 80, 100)
    down = downsample(full, 0.5)
    sig = (down - downsample(ref, 0.5))[vh]
    err = (down - half)[vh]
    assert np.sqrt(np.mean(err**2)) < 0.03 * np.sqrt(np.mean(sig**2))
    # The validity mask shrinks as the view leaves the reference.
    assert vh[-1].mean() < vh[0].mean() <= 1.0


def test_extra_psf_is_a_gaussian_on_top():
    ref = blob(sigma=1.0)
    t, w = pan_gyro(0.0, 0.0)
    fm = ForwardModel(ref, np.array([0.2]), t, w, CAL, t_ref=0.1)
    p, _ = fm.predict(CAL, extra_psf_px=1.5)
    # variances add under convolution (the sampled blob's own variance is measured, not assumed)
    assert moments(p[0])[2] - moments(ref)[2] == pytest.approx(1.5**2, rel=0.01)


def test_matches_the_simulator_fine_time_renderer():
    i = Calibration().intrinsics.scaled(0.5)
    cal = Calibration(width=320, height=240, fx=i.fx, fy=i.fy, cx=i.cx, cy=i.cy)
    motion = mo.sequence([(mo.static(), 0.2), (mo.shake(2.0, 3), None)])
    # A hidden 3 ms time offset: the forward model must agree with the simulator on its sign.
    rec = simulate("texture", motion, 0.5, cal, {"time_offset": 0.003}, seed=0)
    truth_cal = truth_calibration(rec)
    assert truth_cal.time_offset_s == pytest.approx(0.003)
    truth = rec.extras["truth/blurry_noiseless"]
    ref = truth[:8].mean(axis=0)
    t_ref = rec.t[0] + 0.17
    mv = rec.t > t_ref

    def gap(c):
        p, v = predict_frames(ref, rec.t[mv], rec.gyro_t, rec.gyro_rate, c, t_ref=t_ref)
        return float(np.sqrt(np.mean((truth[mv] - p)[v] ** 2) / np.mean((truth[mv] - ref)[v] ** 2)))

    g = gap(truth_cal)
    assert g < 0.05                                              # ≤ 5 % of the motion signal left
    assert gap(truth_cal.replace(tau_s=0.004)) > 2 * g           # the thermal lag matters …
    assert gap(truth_cal.replace(time_offset_s=0.0)) > 2 * g     # … and so does timing,
    assert gap(truth_cal.replace(time_offset_s=-0.003)) > gap(truth_cal.replace(time_offset_s=0.0))  # signed


@pytest.mark.parametrize("readout", [0.0, 0.011])
def test_adjoint_is_the_transpose_of_the_prediction(readout):
    # ⟨A S, c⟩ = ⟨S, Aᵀ c⟩ for the raw prediction (views, IIR, rows read inside steps), on a canvas
    # larger than the frame with a strip of unknown support.
    cal = Calibration(width=80, height=60, fx=200.0, fy=200.0, cx=39.5, cy=29.5, tau_s=0.008,
                      readout_s=readout)
    rng = np.random.default_rng(0)
    t = np.arange(0, 0.3, 0.001)
    w = np.c_[0.3 * np.sin(20 * t), 0.4 * np.sin(13 * t + 1), 0.5 * np.sin(9 * t)]
    fm = ForwardModel(np.zeros((60, 80), np.float32), np.arange(0.1, 0.3, 0.02), t, w, cal, t_ref=0.15,
                      t_start=0.05, max_step_px=1.0)
    S = rng.normal(0, 1, (90, 110)).astype(np.float32)
    sup = np.ones_like(S)
    sup[:5] = 0
    fm.set_reference(S, None, prescaled=True, origin=(15.0, 15.0), support=sup)
    num, _ = fm.predict_raw(cal)
    c = rng.normal(0, 1, num.shape).astype(np.float32)
    lhs = float(np.sum(num.astype(np.float64) * c))
    assert float(np.sum(fm.adjoint(cal, c) * S)) == pytest.approx(lhs, rel=1e-5)


def test_the_views_of_the_last_two_calibrations_are_kept_for_the_current_scene():
    t, w = pan_gyro(0.2, 0.1)
    fm = ForwardModel(blob(x=140.0), np.array([0.2]), t, w, CAL, t_ref=0.1)
    a, b, c = (CAL.replace(time_offset_s=dt) for dt in (0.0, 0.002, 0.004))
    va, vb = fm.views(a)[0], fm.views(b)[0]
    assert fm.views(a)[0] is va and fm.views(b)[0] is vb      # a search's point and its neighbour
    assert fm.views(c)[0] is not va and fm.views(b)[0] is vb  # c took the older one's place (a)
    va2 = fm.views(a)[0]
    assert va2 is not va and np.array_equal(va2, va)          # computed again: the same views
    fm.set_reference(blob(x=120.0))                           # another scene: nothing kept
    assert fm.views(a)[0] is not va2
    small = ForwardModel(blob(x=140.0), np.array([0.2]), t, w, CAL, t_ref=0.1, cache_mb=1e-6)
    assert small.views(a)[0] is not small.views(a)[0]         # no room: nothing kept
