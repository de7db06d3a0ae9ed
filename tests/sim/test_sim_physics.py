"""Simulator physics against closed forms: comet tails, settled static scenes, Eq. 12 stepping,
the Eq. 16/18 forward model, rolling readout, sensor effects and the recording round trip."""

import math

import cv2
import numpy as np
import pytest
from scipy.integrate import cumulative_trapezoid

from thermod.errors import ThermodError
from thermod.io import recording
from thermod.physics.calibration import Calibration
from thermod.physics.geometry import integrate_rotations
from thermod.sim import detector, motion, scenes, synth
from thermod.sim.scenes import BACKGROUND

SMALL = Calibration(width=192, height=144, cx=95.5, cy=71.5)     # paper IFOV, τ = 8 ms, 50 Hz
DEG = math.pi / 180


def render_one(scene_tex, mot, calib=SMALL, t_frames=(10.0,), **kw):
    sc = detector.SphereScene(scene_tex, calib.fx, calib.fy)
    traj = motion.Trajectory(motion.parse(mot), t_frames[0], t_frames[0] - 0.2, t_frames[-1] + 0.05)
    return detector.render(sc, traj, list(t_frames), calib, **kw)


def single_point(h=288, w=384, y=143.3, x=131.6, amp=2000.0, sigma=0.6):
    img = np.full((h, w), BACKGROUND, np.float32)
    yy, xx = np.mgrid[:h, :w]
    img += amp * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * sigma**2)).astype(np.float32)
    return img


def tail_profile(frame, sharp, length=40):
    """Row-summed profile to the right of the point's head (the pan to the right drags the tail +x)."""
    y, x = np.unravel_index(np.argmax(sharp), sharp.shape)
    prof = (frame[y - 4:y + 5] - BACKGROUND).sum(axis=0)
    return prof[x:x + length], x


def fit_decay(prof, d0=4, d1=30):
    d = np.arange(d0, d1)
    slope, _ = np.polyfit(d, np.log(prof[d0:d1]), 1)
    return -1.0 / slope


@pytest.mark.parametrize("tau", [0.008, 0.016])
def test_comet_tail_decays_as_exp_minus_x_over_v_tau(tau):
    calib = SMALL.replace(tau_s=tau)
    r = render_one(single_point(), "pan:50", calib, psf_sigma_px=0)
    prof, x = tail_profile(r.frames[0], r.sharp[0])
    xn = (x - calib.cx) / calib.fx
    v = calib.fx * 50 * DEG * (1 + xn * xn)                 # yaw flow at this column (px/s)
    L = fit_decay(prof)
    assert L == pytest.approx(v * tau, rel=0.01)                 # measured: 0.1 % low
    # the tail is on the side the scene came from; nothing ahead of the head
    y = int(np.argmax(r.sharp[0].max(axis=1)))
    ahead = r.frames[0][y - 4:y + 5, x - 10:x - 3] - BACKGROUND
    assert np.abs(ahead).max() < 1e-3 * prof.max()
    # energy is conserved: the detector redistributes, it does not gain or lose flux
    e_blur = (r.frames[0] - BACKGROUND)[y - 6:y + 7, x - 8:x + 130].sum()
    e_sharp = (r.sharp[0] - BACKGROUND)[y - 6:y + 7, x - 8:x + 8].sum()
    assert e_blur == pytest.approx(e_sharp, rel=0.01)


def test_static_scene_is_unchanged_by_the_detector():
    tex = scenes.texture(288, 384, seed=1)
    calib = SMALL.replace(readout_s=0.012)
    r = render_one(tex, "static", calib, t_frames=(10.0, 10.02, 10.04), psf_sigma_px=0)
    assert r.n_steps == 3                                    # no motion → one step per segment
    for k in range(3):
        np.testing.assert_allclose(r.frames[k], r.sharp[k], atol=0.02)
    # and the sharp view at t_ref is the texture itself around the optical axis (the equirectangular
    # sphere map departs from the pinhole by f·(x − atan x) ≈ 0.004 px within ±30 px of the centre;
    # OpenCV interpolates at 1/32 px, worth ~1 count on the sharpest edges)
    cy, cx = (288 - 144) // 2, (384 - 192) // 2
    d = r.sharp[0][42:102, 66:126] - tex[cy + 42:cy + 102, cx + 66:cx + 126]
    assert np.abs(d).max() < 2.0 and np.sqrt(np.mean(d**2)) < 0.3


def test_eq12_step_rule_removes_stepping():
    img = single_point()
    ripple = {}
    for step in (0.5, 6.0):
        r = render_one(img, "pan:50", psf_sigma_px=0, step_px=step)
        prof, _ = tail_profile(r.frames[0], r.sharp[0])
        d = np.arange(4, 30)
        fit = np.exp(np.polyval(np.polyfit(d, np.log(prof[4:30]), 1), d))
        ripple[step] = float(np.std(prof[4:30] / fit - 1))
        if step == 0.5:
            assert r.max_step_px <= 0.5
    assert ripple[0.5] < 0.005                                  # measured 0.07 %
    assert ripple[6.0] > 100 * ripple[0.5]                      # 6 px steps: a comb of dots


def reference_blur(sharp_k, t_k, traj, calib, m=8.0, n=4000):
    """Eq. 16/18 by brute force: B(p) = Σ w_i S_k(π(K Q_i K⁻¹ p)), Q_i = R(t_k)ᵀR(t_i) from
    geometry.integrate_rotations on densely sampled true rates, w_i ∝ exp(−Δt/τ) Δt."""
    t = np.linspace(t_k - m * calib.tau_s, t_k, n)
    Q = integrate_rotations(t, traj.omega(t), t_k)
    dt = np.gradient(t)
    w = np.exp(-(t_k - t) / calib.tau_s) * dt
    w /= w.sum()
    K = calib.K
    acc = np.zeros_like(sharp_k, dtype=np.float64)
    for i in range(0, n, 4):             # every 4th sample (steps ≪ 0.5 px), weights renormalised below
        H = K @ Q[i] @ np.linalg.inv(K)
        acc += w[i] * cv2.warpPerspective(sharp_k, H, sharp_k.shape[::-1],
                                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                          borderMode=cv2.BORDER_REPLICATE)
    return acc / w[::4].sum()


def test_blur_matches_rotation_homography_model_with_roll():
    """DESIGN §1 sign check: the simulated frame equals the kernel model applied to the sharp truth."""
    tex = scenes.texture(288, 384, seed=2)
    mot = motion.Pan((8 * DEG, 20 * DEG, 60 * DEG))          # pitch + yaw + strong roll
    calib = SMALL
    traj = motion.Trajectory(mot, 10.0, 9.8, 10.05)
    sc = detector.SphereScene(tex, calib.fx)
    r = detector.render(sc, traj, [10.0], calib, psf_sigma_px=0)
    ref = reference_blur(r.sharp[0], 10.0, traj, calib)
    m = 40                                                   # content that left the frame is not in S_k
    res = (r.frames[0] - ref)[m:-m, m:-m]
    blur = (r.frames[0] - r.sharp[0])[m:-m, m:-m]
    assert np.sqrt(np.mean(blur**2)) > 10                    # there is real blur to explain …
    assert np.sqrt(np.mean(res**2)) < 0.02 * np.sqrt(np.mean(blur**2))   # … the model explains it (0.3 %)
    # a wrong sign (the blur running the other way) does not
    traj_rev = motion.Trajectory(motion.Pan(tuple(-np.array(mot.rate))), 10.0, 9.8, 10.05)
    wrong = reference_blur(r.sharp[0], 10.0, traj_rev, calib)
    assert np.sqrt(np.mean(((r.frames[0] - wrong)[m:-m, m:-m]) ** 2)) > 0.5 * np.sqrt(np.mean(blur**2))


def test_rolling_readout_shears_rows_by_speed_times_row_delay():
    tex = scenes.texture(288, 384, seed=3)
    ro = 0.012
    ra = render_one(tex, "pan:50", SMALL, psf_sigma_px=0)
    rb = render_one(tex, "pan:50", SMALL.replace(readout_s=ro), psf_sigma_px=0)
    assert ra.sharp_rolling is None
    np.testing.assert_array_equal(ra.sharp, rb.sharp)                # the global truth is the same
    v = SMALL.fx * 50 * DEG
    for a, b in ((ra.frames[0], rb.frames[0]), (ra.sharp[0], rb.sharp_rolling[0])):
        for r0, r1 in ((0, 24), (60, 84), (120, 144)):
            win = cv2.createHanningWindow((160, r1 - r0), cv2.CV_64F)
            pa, pb = (x[r0:r1, 16:-16].astype(np.float64) for x in (a, b))
            (dx, dy), _ = cv2.phaseCorrelate(pa - pa.mean(), pb - pb.mean(), win)
            rows = np.arange(r0, r1)
            expect = v * ro * np.mean(1 - (rows + 1) / SMALL.height)   # earlier rows: scene further right
            assert dx == pytest.approx(expect, abs=0.35)
            assert abs(dy) < 0.3
    # the last row is read at t_k: the rolling truth's last row is the global truth's
    np.testing.assert_allclose(rb.sharp_rolling[0][-1], rb.sharp[0][-1], atol=1.0)


def test_photon_detector_is_a_box_streak():
    exposure = 0.01
    r = render_one(single_point(), "pan:50", psf_sigma_px=0, kind="photon", exposure_s=exposure)
    prof, _ = tail_profile(r.frames[0], r.sharp[0])
    v = SMALL.fx * 50 * DEG
    length = np.sum(prof > 0.5 * np.median(prof[3:int(v * exposure) - 3]))
    assert length == pytest.approx(v * exposure, abs=1.5)
    flat = prof[3:int(v * exposure) - 3]
    assert flat.std() / flat.mean() < 0.03
    assert prof[int(v * exposure) + 3:].max() < 0.01 * flat.mean()


@pytest.mark.parametrize("readout_s", [0.0, 0.012])
def test_photon_exposure_longer_than_the_frame_period_keeps_a_static_scene_level(readout_s):
    """A 100 ms exposure at 50 Hz spans five frame periods: each row still integrates the whole
    window, so a static scene comes out at its own level (the box average of identical views)."""
    calib = SMALL.replace(readout_s=readout_s)
    tex = np.full((288, 384), 1000.0, np.float32)
    frames = 10.0 + np.arange(4) / calib.frame_rate_hz
    r = render_one(tex, "static", calib, t_frames=tuple(frames), psf_sigma_px=0, kind="photon",
                   exposure_s=0.1)
    np.testing.assert_allclose(r.frames, 1000.0, rtol=1e-5)
    textured = scenes.texture(288, 384, seed=2)
    r = render_one(textured, "static", calib, t_frames=tuple(frames), psf_sigma_px=0, kind="photon",
                   exposure_s=0.1)
    np.testing.assert_allclose(r.frames, r.sharp, rtol=1e-4, atol=0.05)


def test_photon_default_exposure_is_one_frame_period():
    r_default = render_one(single_point(), "pan:50", psf_sigma_px=0, kind="photon")
    r_period = render_one(single_point(), "pan:50", psf_sigma_px=0, kind="photon",
                          exposure_s=1.0 / SMALL.frame_rate_hz)
    np.testing.assert_array_equal(r_default.frames, r_period.frames)


def test_time_compression_matches_fine_time_render():
    """The paper's synthesis (slow sharp views re-timed c× faster through Eq. 10) equals the
    fine-time render of the fast motion."""
    tex = scenes.texture(288, 384, seed=4)
    calib = SMALL
    c = 20.0
    fast = render_one(tex, "pan:40", calib, psf_sigma_px=0).frames[0]
    # slow camera at 2 °/s: views 1/1000 s apart are 0.05 px apart, re-timed to 50 µs at 40 °/s
    h_slow = 1e-3
    t = 10.0 + np.arange(-int(6 * calib.tau_s * c / h_slow), 1) * h_slow
    traj = motion.Trajectory(motion.parse(f"pan:{40 / c}"), t[-1], t[0] - 0.01, t[-1] + 0.01)
    sc = detector.SphereScene(tex, calib.fx)
    views = np.stack([sc.view(R, calib.K, calib.width, calib.height) for R in traj.R(t)[::2]])
    out = detector.time_compress(views, 2 * h_slow, c, calib.tau_s)
    blur = fast - views[-1]
    res = (out[-1] - fast)[8:-8, 8:-8]
    assert np.sqrt(np.mean(res**2)) < 0.03 * np.sqrt(np.mean(blur[8:-8, 8:-8] ** 2))


# ----------------------------------------------------------------------------- simulate()

def test_simulate_round_trips_through_recording(tmp_path):
    rec = synth.simulate("bars", "slew:60", 0.1, SMALL, effects={"time_offset": 0.004, "gyro_bias": 0.002},
                         seed=5)
    assert rec.frames.dtype == np.uint16 and rec.frames.shape == (5, 144, 192)
    np.testing.assert_allclose(np.diff(rec.t), 0.02)
    assert rec.gyro_t[0] < rec.t[0] - 5 * SMALL.tau_s and rec.gyro_t[-1] > rec.t[-1]
    path = tmp_path / "sim.h5"
    recording.write(path, rec)
    back = recording.read(path)
    np.testing.assert_array_equal(back.frames, rec.frames)
    np.testing.assert_array_equal(back.gyro_rate, rec.gyro_rate)
    np.testing.assert_array_equal(back.extras["truth/frames"], rec.extras["truth/frames"])
    assert back.calibration == SMALL                            # nominal calibration in the attrs
    true = synth.truth_calibration(back)
    assert true.time_offset_s == pytest.approx(0.004)
    assert true.bias_rad_s == pytest.approx((0.002,) * 3)
    assert back.extra_attrs["truth"]["effects"] == "gyro_bias,time_offset"


def test_time_offset_effect_shifts_gyro_clock():
    rec = synth.simulate("texture", "slew:90:yaw:0.05:0.02", 0.1, SMALL, effects={"time_offset": 0.004})
    true = synth.truth_calibration(rec)
    t_cam, w = true.gyro_to_camera(rec.gyro_t, rec.gyro_rate)
    np.testing.assert_allclose(t_cam, rec.extras["truth/gyro_t_camera"], atol=1e-9)
    np.testing.assert_allclose(w, rec.extras["truth/gyro_omega_camera"], atol=1e-5)
    # with the nominal calibration the ramps are 4 ms late: the rate error is the slope × 4 ms
    t_nom, w_nom = rec.calibration.gyro_to_camera(rec.gyro_t, rec.gyro_rate)
    peak_slope = np.abs(np.gradient(w[:, 1], t_cam)).max()
    assert np.abs(w_nom[:, 1] - np.interp(t_nom, t_cam, w[:, 1])).max() == pytest.approx(
        peak_slope * 0.004, rel=0.1)


def test_time_constant_and_psf_effects_change_frames_the_right_way():
    base = synth.simulate("points", "pan:50", 0.04, SMALL, seed=1, truth=True)
    slow = synth.simulate("points", "pan:50", 0.04, SMALL, seed=1, effects={"time_constant": 0.016})
    blurred = synth.simulate("points", "static", 0.04, SMALL, seed=1, effects={"optical_psf": 1.5})
    sharp = base.extras["truth/frames"][-1][:, :96]                  # a point with room for its tail
    y, x = np.unravel_index(np.argmax(sharp), sharp.shape)
    p0 = base.extras["truth/blurry_noiseless"][-1][y, x:x + 40] - BACKGROUND
    p1 = slow.extras["truth/blurry_noiseless"][-1][y, x:x + 40] - BACKGROUND
    assert fit_decay(p1) / fit_decay(p0) == pytest.approx(2.0, rel=0.05)
    # static + PSF: exactly the Gaussian-blurred sharp view
    b = blurred.extras["truth/blurry_noiseless"][-1]
    np.testing.assert_allclose(b, detector.gaussian_psf(blurred.extras["truth/frames"][-1], 1.5), atol=0.05)
    assert b.max() < 0.3 * blurred.extras["truth/frames"][-1].max() + 0.7 * BACKGROUND


def test_sensor_effects_statistics():
    fx = {"netd": 0.05, "fpn": 0.2, "quantisation_bits": 14}
    rec = synth.simulate("texture", "static", 0.2, SMALL, effects=fx, seed=3)
    f = rec.frames.astype(np.float64)
    clean = rec.extras["truth/blurry_noiseless"].astype(np.float64)
    assert np.all(rec.frames % 4 == 0)                               # 14-bit ADC on the 16-bit scale
    cpk = scenes.COUNTS_PER_K
    temporal = np.std(np.diff(f, axis=0)) / np.sqrt(2)
    assert temporal == pytest.approx(math.sqrt((0.05 * cpk) ** 2 + 16 / 12), rel=0.05)
    fixed = (f - clean).mean(axis=0)
    assert np.std(fixed) == pytest.approx(0.2 * cpk, rel=0.05)
    # gain non-uniformity scales the deviation from the reference level
    g = synth.simulate("texture", "static", 0.02, SMALL, effects={"gain_nonuniformity": 0.05}, seed=3)
    clean = g.extras["truth/blurry_noiseless"][0].astype(np.float64)
    ref = float(np.median(scenes.texture(288, 384, seed=3)))
    d = clean - ref
    sel = np.abs(d) > 200
    gains = (g.frames[0][sel] - ref) / d[sel]
    assert np.std(gains) == pytest.approx(0.05, rel=0.15)


def test_detector_nonlinearity_is_quadratic():
    c = 0.05
    rec = synth.simulate("texture", "static", 0.02, SMALL, effects={"detector_nonlinearity": c}, seed=3)
    clean = rec.extras["truth/blurry_noiseless"][0].astype(np.float64)
    ref = float(np.median(scenes.texture(288, 384, seed=3)))
    d = clean - ref
    dev = rec.frames[0] - clean
    coef = np.polyfit(d.ravel(), dev.ravel(), 2)
    assert coef[0] == pytest.approx(c / 1000, rel=0.02)
    assert abs(coef[1]) < 1e-3


def test_bad_effects_and_specs_raise_clear_errors():
    with pytest.raises(ThermodError, match="--effect warp_drive"):
        synth.simulate("bars", "pan:50", 0.02, SMALL, effects={"warp_drive": 1})
    with pytest.raises(ThermodError, match="--effect misalignment: expected 3"):
        synth.simulate("bars", "pan:50", 0.02, SMALL, effects={"misalignment": 0.01})
    with pytest.raises(ThermodError, match="--motion"):
        synth.simulate("bars", "wobble:3", 0.02, SMALL)
    with pytest.raises(ThermodError, match="--scene"):
        synth.simulate("nothing-here", "pan:50", 0.02, SMALL)
    with pytest.raises(ThermodError, match=r"width: expected an integer in \[1, "):   # Calibration's own
        synth.simulate("bars", "pan:50", 0.02, SMALL.replace(width=0))
    with pytest.raises(ThermodError, match="quantisation_bits"):
        synth.simulate("bars", "pan:50", 0.02, SMALL, effects={"quantisation_bits": 14.5})
    with pytest.raises(ThermodError, match="readout_s"):
        synth.simulate("bars", "pan:50", 0.1, SMALL, effects={"rolling_readout": 0.05})


# ----------------------------------------------------------------------------- motion

def test_the_recorded_gyro_integrates_to_the_true_attitude_across_a_motion_onset():
    """The README's calibration motion (a static lead-in, then shake): the recorded 1 kHz gyro,
    integrated as every consumer integrates it, gives the truth's frame attitudes to 0.02 mrad (a rate
    step at the onset would leave ½·Δω·Δt, which a fit takes for a gyro bias or a time offset)."""
    from thermod.calib.forward import orientations
    from thermod.physics.geometry import so3_log

    rec = synth.simulate("bars", "static:0.3+shake:4", 0.8, SMALL, seed=0)
    t_cam, w_cam = rec.calibration.gyro_to_camera(rec.gyro_t, rec.gyro_rate.astype(np.float64))
    Q = orientations(rec.t, t_cam, w_cam, rec.t[0])
    R = rec.extras["truth/frame_R"]
    err = [np.linalg.norm(so3_log((R[0].T @ R[k]).T @ Q[k])) for k in range(len(rec.t))]
    assert max(err) < 2e-5, max(err)


def test_motion_specs_and_sequences():
    m = motion.parse("static:0.3+pan:50")
    w = m.omega(np.array([-0.1, 0.1, 0.29, 0.31, 0.33, 2.0]))
    np.testing.assert_allclose(w[:3], 0)
    np.testing.assert_allclose(w[3:, 1], [0.25 * 50 * DEG, 50 * DEG, 50 * DEG])   # raised cosine over 30 ms
    # the rate is continuous at every boundary, so a 1 kHz gyro interpolated linearly integrates to the
    # attitude the fine-time truth has (a step leaves up to ½·Δω·Δt)
    seq = motion.parse("static:0.3+shake:4:0.5+pan:50")
    fine = np.arange(0.0, 1.2, 1e-5)
    t_gyro = np.arange(0.0, 1.2, 1e-3) + 0.37e-3                  # boundaries fall between the samples
    theta_fine = cumulative_trapezoid(seq.omega(fine), fine, axis=0, initial=0.0)
    theta_gyro = cumulative_trapezoid(seq.omega(t_gyro), t_gyro, axis=0, initial=0.0)
    theta_gyro = np.stack([np.interp(fine, t_gyro, theta_gyro[:, a]) for a in range(3)], axis=1)
    drift = (theta_fine - theta_gyro) - (theta_fine - theta_gyro)[np.searchsorted(fine, 0.1)]
    assert np.abs(drift[(fine > 0.1) & (fine < 1.1)]).max() < 6e-5, np.abs(drift).max()   # steps: 3.5e-4
    np.testing.assert_allclose(motion.parse("roll:30").omega(0.0), [[0, 0, 30 * DEG]])
    np.testing.assert_allclose(motion.parse("pan:20:pitch").omega(0.0), [[20 * DEG, 0, 0]])
    s = motion.parse("slew:90:yaw:0.2:0.3")
    np.testing.assert_allclose(s.omega(np.array([-0.1, 0.1, 0.3, 0.6, 0.8]))[:, 1] / DEG, [0, 45, 90, 45, 0],
                               atol=1e-9)
    a = motion.parse("shake:2", seed=1).omega(np.linspace(0, 5, 20001))
    b = motion.parse("shake:2", seed=1).omega(np.linspace(0, 5, 20001))
    np.testing.assert_array_equal(a, b)                                       # seeded, reproducible
    angle = np.cumsum(a, axis=0) * (5 / 20000)
    assert np.std(angle[:, 1]) / DEG == pytest.approx(2.0, rel=0.35)
    v = motion.parse("vibration:10:45").omega(np.linspace(0, 2, 40001))
    assert np.sqrt(np.mean(v[:, 2] ** 2)) / DEG == pytest.approx(10.0, rel=0.1)
    for bad in ("pan:fast", "slew:90:sideways", "static+pan:50", "pan:50+static"):
        with pytest.raises(ThermodError, match="--motion"):
            motion.parse(bad)


def test_sway_returns_to_start_and_trajectory_matches_geometry():
    m = motion.parse("sway:3:1.0")
    traj = motion.Trajectory(m, 0.0, -0.1, 1.1)
    assert np.abs(traj.R(1.0)[0] - np.eye(3)).max() < 1e-6
    th = m.theta(0.37)[0]
    from thermod.physics.geometry import so3_exp
    R0 = so3_exp(m.theta(0.0)[0])
    np.testing.assert_allclose(traj.R(0.37)[0], R0.T @ so3_exp(th), atol=1e-7)
    # geometry.integrate_rotations on the same rates agrees (Q = R(t_ref)ᵀ R(t_i))
    t = np.linspace(0.2, 0.5, 3001)
    Q = integrate_rotations(t, m.omega(t), 0.5)
    np.testing.assert_allclose(Q[0], traj.R(0.5)[0].T @ traj.R(0.2)[0], atol=1e-7)


def test_gyro_log_replay(shared_data, require):
    require((shared_data / "gyro" / "betaflight_smooth_2khz.csv").exists(), "shared/data gyro log")
    log = motion.load_gyro_log(shared_data / "gyro" / "betaflight_smooth_2khz.csv")
    assert log.t_log[0] == 0 and np.all(np.diff(log.t_log) > 0)
    assert np.median(np.diff(log.t_log)) == pytest.approx(505e-6, rel=0.02)   # junk rows skipped
    assert 38 < log.t_log[-1] < 40
    # roll (body x) → camera z, pitch → camera x, yaw → camera y
    np.testing.assert_allclose(log.omega(0.0)[0] / DEG, [5, 0, 2])
    m = motion.parse("log:10")
    assert m.omega(0.0)[0] == pytest.approx(log.omega(10.0)[0])


def test_simulate_time_compression_option_matches_fine_render():
    kw = dict(seed=4, effects={"optical_psf": 0.0})
    fine = synth.simulate("texture", "pan:30", 0.04, SMALL, **kw)
    tc = synth.simulate("texture", "pan:30", 0.04, SMALL, method="time_compression", compression=40,
                        slow_fps=50, **kw)
    a, b = fine.extras["truth/blurry_noiseless"], tc.extras["truth/blurry_noiseless"]
    blur = a - fine.extras["truth/frames"]
    res = (b - a)[:, 8:-8, 8:-8]
    # views 0.5 ms apart at 30 °/s move 0.38 px: below Eq. 12's 1 px, so no stepping
    assert tc.extra_attrs["truth"]["max_step_px"] == pytest.approx(SMALL.fx * 30 * DEG / 2000, rel=0.02)
    assert np.sqrt(np.mean(res**2)) < 0.05 * np.sqrt(np.mean(blur[:, 8:-8, 8:-8] ** 2))
    np.testing.assert_allclose(tc.extras["truth/frames"], fine.extras["truth/frames"], atol=1.0)
    with pytest.raises(ThermodError, match="whole number"):
        synth.simulate("texture", "pan:30", 0.04, SMALL, method="time_compression", compression=7.3)
    with pytest.raises(ThermodError, match="rolling readout"):
        synth.simulate("texture", "pan:30", 0.04, SMALL, method="time_compression",
                       effects={"rolling_readout": 0.01})


def test_contract_constructors():
    seq = motion.sequence([(motion.static(), 0.1), (motion.pan(20, "pitch"), None)])
    np.testing.assert_allclose(seq.omega(np.array([0.05, 0.2])), [[0, 0, 0], [20 * DEG, 0, 0]])
    assert seq.spec == "static+pan:20:pitch"
    with pytest.raises(ThermodError, match="duration"):
        motion.sequence([(motion.static(), None), (motion.pan(), None)])


def test_gyro_side_effects_through_simulate():
    mot = "pan:40:pitch"
    fx = {"gyro_scale": (1.05, 1.0, 0.97), "misalignment": (0.0, 0.0, 0.02),
          "gyro_bias": (0.001, -0.002, 0.0)}
    rec = synth.simulate("bars", mot, 0.04, SMALL, effects=fx, truth=False)
    true = synth.truth_calibration(rec)
    w_true = rec.extras["truth/gyro_omega_camera"]
    np.testing.assert_allclose(true.gyro_to_camera(rec.gyro_t, rec.gyro_rate)[1], w_true, atol=1e-5)
    _, w_nom = rec.calibration.gyro_to_camera(rec.gyro_t, rec.gyro_rate)
    # raw = scale⁻¹ Rᵀ ω + bias: the nominal model sees pitch/1.05 and 2 % of it leaking into yaw
    w0 = 40 * DEG
    assert np.median(w_nom[:, 0]) == pytest.approx(w0 * math.cos(0.02) / 1.05 + 0.001, rel=1e-4)
    assert np.median(w_nom[:, 1]) == pytest.approx(-math.sin(0.02) * w0 - 0.002, rel=2e-3)
    assert "truth/frames" not in rec.extras
    # clock drift: stamps run away from camera time at the drift rate; noise: the per-sample RMS
    rec = synth.simulate("bars", "static", 0.5, SMALL,
                         effects={"clock_drift_ppm": 200.0, "gyro_noise": 0.002})
    lag = rec.extras["truth/gyro_t_camera"] - rec.gyro_t
    assert np.polyfit(rec.gyro_t, lag, 1)[0] == pytest.approx(200e-6, rel=1e-3)
    assert np.std(rec.gyro_rate) == pytest.approx(0.002, rel=0.05)
    # the chip's low-pass delays a ramp by its group delay √2/(2π f_c)
    rec = synth.simulate("bars", "slew:90:yaw:0.2:0.1", 0.3, SMALL, effects={"gyro_lowpass_hz": 50.0},
                         truth=False)
    t, w = rec.gyro_t, rec.gyro_rate[:, 1].astype(np.float64)
    ramp = (t > rec.t[0] + 0.07) & (t < rec.t[0] + 0.13)                   # middle of the ramp-up
    lagged = np.interp(t[ramp], rec.extras["truth/gyro_t_camera"],
                       rec.extras["truth/gyro_omega_camera"][:, 1])
    slope = np.gradient(lagged, t[ramp])
    assert np.median((lagged - w[ramp]) / slope) == pytest.approx(math.sqrt(2) / (2 * math.pi * 50), rel=0.05)


def test_scenes(tmp_path, monkeypatch, shared_data, caplog):
    b = scenes.load_scene("bars", (192, 256))
    assert b.dtype == np.float32 and b.shape == (192, 256)
    assert b.min() == BACKGROUND and b.max() == pytest.approx(BACKGROUND + 5 * scenes.COUNTS_PER_K)  # 5 K
    assert 0.02 < np.mean(b > BACKGROUND) < 0.3
    p = scenes.load_scene("points", (192, 256), seed=1)
    assert np.sum(p > BACKGROUND + 100) > 4
    t1, t2 = scenes.load_scene("texture", (96, 128), seed=1), scenes.load_scene("texture", (96, 128), seed=2)
    assert np.array_equal(t1, scenes.load_scene("texture", (96, 128), seed=1)) and not np.array_equal(t1, t2)
    # a 16-bit PNG path, mirror-padded to the requested size
    img = (np.arange(40 * 50).reshape(40, 50) + 17000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "s.png"), img)
    s = scenes.load_scene(str(tmp_path / "s.png"), (60, 50))
    assert s.shape == (60, 50) and np.array_equal(s[10:50], img.astype(np.float32))
    if (shared_data / "thermal").is_dir():
        r = scenes.load_scene("real:0", (480, 640))
        assert r.shape == (512, 640) and 17000 < np.median(r) < 19000
    # without shared/data, "real" falls back to the procedural texture
    monkeypatch.setenv("THERMOD_SHARED_DATA", str(tmp_path / "nothing"))
    assert scenes.shared_data_dir() is None
    with caplog.at_level("WARNING", logger="thermod.sim.scenes"):
        np.testing.assert_array_equal(scenes.load_scene("real", (96, 128), seed=1), t1)
    assert "using the procedural 'texture' scene" in caplog.text
    with pytest.raises(ThermodError, match="--scene"):
        scenes.load_scene(str(tmp_path / "missing.png"), (96, 128))


@pytest.mark.parametrize("mot, tol", [("pan:50", 0.03), ("shake:1", 0.03), ("roll:60", 0.06)])
def test_thermod_kernels_explain_the_simulation(mot, tol):
    """DESIGN §1 end to end: kernels rendered from the simulated RAW gyro with the true calibration,
    applied to the sharp truth, reproduce the simulated blurry frame (measured: 1.9 %, 2.2 % and 4.2 %
    of the blur's RMS — under roll the blur varies within each grid cell; the kernels also cut the
    exponential at 5τ)."""
    from thermod.physics import kernels
    rec = synth.simulate("texture", mot, 0.06, SMALL, seed=1)
    k = rec.n_frames - 1
    sharp, blurry = rec.extras["truth/frames"][k], rec.extras["truth/blurry_noiseless"][k]
    grid = kernels.render_kernel_grid(rec.gyro_t, rec.gyro_rate, synth.truth_calibration(rec), rec.t[k],
                                      grid=(12, 16))
    m = 24
    res = (blurry - kernels.blur_varying(sharp, grid))[m:-m, m:-m]
    blur = (blurry - sharp)[m:-m, m:-m]
    assert np.sqrt(np.mean(res**2)) < tol * np.sqrt(np.mean(blur**2))
