"""Blur-kernel renderer (Eq. 17, 18, 19): numbers, signs and geometry.

The sign convention is checked end to end against a fine-time simulation made here: the sharp view
at t_k warped by H = K Q(s) K⁻¹ at 25 µs steps (Q integrated from the analytic rate, independent of
the renderer) and exponentially averaged. Blurring the same sharp view with the rendered kernel must
give the same frame to within 1 % of the scene's contrast.
"""

import math

import cv2
import numpy as np
import pytest
from scipy import integrate, ndimage

from thermod.errors import ThermodError
from thermod.physics import kernels as K
from thermod.physics.calibration import Calibration
from thermod.physics.detector import row_read_time
from thermod.physics.geometry import integrate_rotations, so3_exp
from thermod.sim.reference_kernels import render_thermal_kernel_reference

DEG = math.pi / 180.0
CAL = Calibration()                        # the paper's camera: IFOV 0.0391°, τ = 8 ms
F = CAL.fx                                 # px per rad at the centre (≈ 1465)
TAU = CAL.tau_s
# mean of Δ = t_k − s under exp(−Δ/τ) truncated to [0, mτ], in units of τ
TRUNC_MEAN_5 = 1.0 - 5.0 * math.exp(-5.0) / (1.0 - math.exp(-5.0))
SMALL = Calibration(width=320, height=240, cx=159.5, cy=119.5)


def gyro_const(rate_cam, t0=0.0, t1=0.1, hz=1000.0):
    t = np.arange(t0, t1 + 0.5 / hz, 1.0 / hz)
    r = np.tile(np.asarray(rate_cam, np.float32), (len(t), 1))
    return t, r


def gyro_from(fn, t0=0.0, t1=0.1, hz=1000.0):
    t = np.arange(t0, t1 + 0.5 / hz, 1.0 / hz)
    return t, np.asarray([fn(s) for s in t], np.float32)


def yaw(rate):
    return (0.0, rate, 0.0)


# ----------------------------------------------------------------------------------- reference
def test_jitted_core_arguments_follow_their_named_layouts():
    """The renderer passes plain tuples (fast numba dispatch); the core reads them by field name."""
    from thermod.physics.kernels import core, params, render
    p = params.params(CAL)
    win, smp = render._path_args(p, 0.1, 0.14, False, 1500.0)
    assert core.PathWindow(*win) == core.PathWindow(start=0.1, end=0.14, tau=CAL.tau_s, box=False)
    assert core.PathSampling(*smp) == core.PathSampling(px_per_rad=1500.0, max_step_px=K.MAX_STEP_PX,
                                                        max_nodes=K.MAX_NODES, max_size_px=p.max_size_px)
    win, _ = render._path_args(p, 0.1, 0.14, True, 1500.0)
    assert core.PathWindow(*win).box and core.PathWindow(*win).tau == 1.0
    assert core.Pinhole(*p.camera) == core.Pinhole(fx=CAL.fx, fy=CAL.fy, cx=CAL.cx, cy=CAL.cy)


@pytest.mark.parametrize("case", ["yaw_fast", "mixed_offcentre", "psf", "coverage", "calib", "readout"])
def test_numba_matches_numpy_reference(case):
    rng = np.random.default_rng(1)
    cal, point, psf, tf = CAL, None, False, 0.0705
    t, r = gyro_from(lambda s: (0.6 * math.sin(40 * s), 1.2 * math.cos(25 * s), 0.9 * math.sin(31 * s + 1)))
    if case == "yaw_fast":
        t, r = gyro_const(yaw(100 * DEG))
    elif case == "mixed_offcentre":
        point = (600.3, 20.7)
    elif case == "psf":
        psf, point = True, (100.0, 400.0)
    elif case == "coverage":
        tf = 0.1153                        # gyro ends at 0.1: rate held, coverage < 1
    elif case == "calib":
        r = r + rng.normal(0, 0.2, r.shape).astype(np.float32)
        cal = CAL.replace(bias_rad_s=(0.1, -0.2, 0.05), scale=(1.1, 0.9, 1.02), time_offset_s=0.0023
                          ).with_misalignment((0.1, -0.3, 0.7))
    elif case == "readout":
        cal, point = CAL.replace(readout_s=0.012), (50.0, 10.0)
    k = K.render_thermal_kernel(t, r, cal, tf, point=point, psf=psf)
    ref = render_thermal_kernel_reference(t, r, cal, tf, point=point, psf=psf)
    assert k.weights.dtype == np.float32
    assert k.weights.shape == ref.weights.shape and k.origin == ref.origin
    np.testing.assert_allclose(k.weights, ref.weights, atol=1e-5)
    assert k.coverage == pytest.approx(ref.coverage, abs=1e-9)
    assert k.n_samples == ref.n_samples
    assert float(k.weights.sum()) == pytest.approx(1.0, abs=1e-5)
    if case == "coverage":
        # 15.3 ms of the 40 ms window lie beyond the last sample: coverage = ∫ exp over the rest
        expect = (math.exp(-15.3 / 8) - math.exp(-5)) / (1 - math.exp(-5))
        assert k.coverage == pytest.approx(expect, rel=1e-6)
        assert k.n_samples == 25                      # samples 0.076 … 0.100 in (0.0753, 0.1153]
    else:
        assert k.coverage == pytest.approx(1.0)
        assert k.n_samples == 40


def test_path_matches_integrate_rotations_at_samples_and_is_finely_sampled():
    """At gyro stamps the path equals the reference rate semantics; between them splats are < 0.5 px."""
    t, r = gyro_from(lambda s: (1.5 * math.sin(30 * s), -3.0 + 20 * s, 2.0 * math.cos(17 * s)))
    point = (500.0, 60.0)
    path = K.render_path(t, r, CAL, 0.0603, point=point)
    assert path.w.sum() == pytest.approx(1.0, abs=1e-12) and (path.w > 0).all()
    assert np.all(np.diff(path.t) > 0) and path.t[-1] == pytest.approx(0.0603)
    assert path.t[0] == pytest.approx(0.0603 - 5 * TAU)
    steps = np.linalg.norm(np.diff(path.u, axis=0), axis=1)
    assert steps.max() < 0.5
    assert len(path.t) > 2 * 40                    # ~3 rad/s ≈ 4.4 px/ms: several splats per sample
    Q = integrate_rotations(t, r.astype(np.float64), 0.0603)
    Kc, Ki = CAL.K, np.linalg.inv(CAL.K)
    for i in np.nonzero((t > 0.0603 - 0.04) & (t < 0.0603))[0]:
        j = int(np.argmin(np.abs(path.t - t[i])))
        assert path.t[j] == pytest.approx(t[i], abs=1e-12)
        q = Kc @ Q[i] @ Ki @ np.array([point[0], point[1], 1.0])
        np.testing.assert_allclose(path.u[j], np.array(point) - q[:2] / q[2], atol=1e-9)


# ------------------------------------------------------------------------------ basic geometry
def test_yaw_pan_gives_exponential_tail_to_the_right():
    v = 30 * DEG                                   # rad/s → v·f ≈ 767 px/s, v·f·τ ≈ 6.1 px
    t, r = gyro_const(yaw(v))
    k = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=False)
    assert k.weights.shape[0] == 1 and k.origin == (0, 0)          # purely horizontal, starts at 0
    assert k.weights.sum() == pytest.approx(1.0, abs=1e-6)
    uy, ux = k.centroid
    assert uy == 0.0
    assert ux == pytest.approx(F * v * TAU * TRUNC_MEAN_5, rel=2e-3)  # mean offset ≈ v τ (5τ window)
    assert k.extent_px == pytest.approx(F * math.tan(v * 5 * TAU), abs=1.01)
    # exponential decay with length v τ (px): fit log weights away from both ends
    w = k.weights[0].astype(np.float64)
    x = np.arange(2, 26)
    slope = np.polyfit(x, np.log(w[x]), 1)[0]
    assert -1.0 / slope == pytest.approx(F * v * TAU, rel=0.01)
    # a long window: the mean offset is v τ itself
    k20 = K.render_thermal_kernel(t, r, CAL, 0.0999, m=11.0, psf=False)
    m11 = 1.0 - 11.0 * math.exp(-11.0) / (1.0 - math.exp(-11.0))
    assert k20.centroid[1] == pytest.approx(F * v * TAU * m11, rel=2e-3)
    assert k20.centroid[1] == pytest.approx(F * v * TAU, rel=3e-3)
    # opposite rate → mirror image
    kn = K.render_thermal_kernel(*gyro_const(yaw(-v)), CAL, 0.0605, psf=False)
    np.testing.assert_allclose(kn.weights[0, ::-1], k.weights[0], atol=1e-6)
    assert kn.origin == (0, k.weights.shape[1] - 1)


def test_pitch_moves_the_kernel_up():
    v = 20 * DEG
    k = K.render_thermal_kernel(*gyro_const((v, 0, 0)), CAL, 0.0605, psf=False)
    assert k.weights.shape[1] == 1                 # purely vertical
    uy, ux = k.centroid
    assert ux == 0.0
    # rotation about camera x (right) by +ω: the past view looked down → content at p − u, u_y < 0
    assert uy == pytest.approx(-F * v * TAU * TRUNC_MEAN_5, rel=2e-3)


def test_roll_zero_at_centre_tangential_off_centre():
    v = 40 * DEG
    t, r = gyro_const((0, 0, v))
    k0 = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=False)
    assert k0.weights.shape == (1, 1) and k0.weights[0, 0] == pytest.approx(1.0)
    assert k0.extent_px == 0.0
    # 200 px right of centre: tangential (vertical) blur of length 200·ω·t
    k = K.render_thermal_kernel(t, r, CAL, 0.0605, point=(CAL.cx + 200, CAL.cy), psf=False)
    uy, ux = k.centroid
    assert uy == pytest.approx(200 * v * TAU * TRUNC_MEAN_5, rel=3e-3)
    assert abs(ux) < 0.01 * abs(uy)
    # 200 px above centre: tangential is horizontal
    k = K.render_thermal_kernel(t, r, CAL, 0.0605, point=(CAL.cx, CAL.cy - 200), psf=False)
    uy, ux = k.centroid
    assert ux == pytest.approx(200 * v * TAU * TRUNC_MEAN_5, rel=3e-3)
    assert abs(uy) < 0.01 * abs(ux)


def test_kernels_sum_to_one_for_many_motions():
    rng = np.random.default_rng(7)
    for _ in range(20):
        r = rng.normal(0, 1.0, (101, 3)).astype(np.float32)
        t = np.arange(101) * 1e-3
        k = K.render_thermal_kernel(t, r, CAL, rng.uniform(0.0, 0.12), point=rng.uniform(0, 480, 2))
        assert k.weights.dtype == np.float32
        assert float(k.weights.sum(dtype=np.float64)) == pytest.approx(1.0, abs=1e-5)
        assert (k.weights >= 0).all()


def test_big_kernel_is_not_cropped():
    v = 100 * DEG                                  # the spec's example: 100 °/s, τ = 8 ms → 100+ px
    t, r = gyro_const(yaw(v))
    k = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=False)
    expect = F * math.tan(v * 5 * TAU)
    assert expect > 100
    assert k.extent_px == pytest.approx(expect, abs=1.01)
    assert k.weights.shape == (1, int(math.floor(expect)) + 2)
    assert k.weights.sum() == pytest.approx(1.0, abs=1e-5)
    # no dotted kernel (stepping, Eq. 12): every pixel along the path carries weight, smoothly
    w = k.weights[0, :100].astype(np.float64)
    assert (w > 0).all()
    ratio = w[2:] / w[1:-1]                        # (bin 0 only gets half a hat)
    assert np.allclose(ratio, math.exp(-1 / (F * v * TAU)), rtol=0.025)
    kp = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=True)
    g = K.optical_psf(CAL.psf_sigma_px)
    assert kp.weights.shape == (1 + 2 * g.origin[0], k.weights.shape[1] + 2 * g.origin[1])
    assert kp.extent_px >= k.extent_px


def test_photon_kernel_is_a_uniform_segment():
    v = 50 * DEG
    t, r = gyro_const(yaw(v))
    ex = 0.010
    k = K.render_photon_kernel(t, r, CAL, 0.0605, ex, psf=False)
    length = F * math.tan(v * ex)                  # ≈ 12.8 px
    assert k.weights.shape[0] == 1
    assert k.extent_px == pytest.approx(length, abs=1.01)
    assert k.centroid[1] == pytest.approx(length / 2, rel=3e-3)
    inner = k.weights[0, 1:int(length) - 1]
    np.testing.assert_allclose(inner, 1.0 / length, rtol=0.01)
    assert k.coverage == pytest.approx(1.0) and k.n_samples == 10
    # the thermal kernel of the same motion decays from zero displacement instead
    kt = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=False)
    assert kt.weights[0, 1] / kt.weights[0, 8] == pytest.approx(math.exp(7 / (F * v * TAU)), rel=0.03)
    assert k.weights[0, 1] / k.weights[0, 8] == pytest.approx(1.0, abs=0.01)


# ------------------------------------------------------------------------ calibration terms
def test_bias_equal_to_rate_gives_a_delta():
    t, r = gyro_const((0.3, -0.5, 0.2))
    bias = tuple(float(x) for x in r[0])            # the float32 samples' exact values
    k = K.render_thermal_kernel(t, r, CAL.replace(bias_rad_s=bias), 0.0605, psf=False)
    assert k.weights.shape == (1, 1) and k.origin == (0, 0) and k.extent_px == 0.0
    k_no = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=False)
    assert k_no.extent_px > 20
    kp = K.render_thermal_kernel(t, r, CAL.replace(bias_rad_s=bias), 0.0605, psf=True)
    np.testing.assert_array_equal(kp.weights, K.optical_psf(CAL.psf_sigma_px).weights)


def test_R_cam_gyro_90deg_about_z_turns_gyro_x_into_camera_y():
    v = 30 * DEG
    Rz = so3_exp((0, 0, math.pi / 2))
    np.testing.assert_allclose(Rz @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    cal = CAL.replace(R_cam_gyro=tuple(map(tuple, Rz)))
    k = K.render_thermal_kernel(*gyro_const((v, 0, 0)), cal, 0.0605, psf=False)
    direct = K.render_thermal_kernel(*gyro_const((0, v, 0)), CAL, 0.0605, psf=False)
    assert k.weights.shape == direct.weights.shape == (1, direct.weights.shape[1])
    np.testing.assert_allclose(k.weights, direct.weights, atol=1e-6)
    assert k.centroid[1] > 5                      # camera-y rate = horizontal image motion


def test_scale_two_doubles_the_extent():
    t, r = gyro_const((0.1, 0.3, 0.0))
    k1 = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=False)
    k2 = K.render_thermal_kernel(t, r, CAL.replace(scale=(2.0, 2.0, 2.0)), 0.0605, psf=False)
    assert k2.extent_px == pytest.approx(2 * k1.extent_px, rel=0.03)
    np.testing.assert_allclose(k2.centroid, 2 * np.array(k1.centroid), rtol=2e-3)


def _ramp_stop(t_stop, v):
    """Yaw rate v until t_stop, 0 after (one 1 ms linear ramp in between: samples every ms)."""
    return lambda s: (0.0, v if s <= t_stop + 1e-9 else 0.0, 0.0)


def test_time_offset_shifts_which_samples_count():
    v = 40 * DEG
    t, r = gyro_from(_ramp_stop(0.050, v))
    tf = 0.0605

    def analytic_mean(offset):
        # u_x(s) = f·tan(θ(s)), θ(s) = ∫_s^tf ω, ω piecewise linear through the (shifted) samples
        tc = t + offset

        def theta(s):
            return integrate.quad(lambda x: np.interp(x, tc, r[:, 1].astype(float)), s, tf,
                                  points=[0.050 + offset, 0.051 + offset], limit=200)[0]

        num = integrate.quad(lambda s: F * math.tan(theta(s)) * math.exp(-(tf - s) / TAU), tf - 5 * TAU, tf,
                             points=[0.050 + offset, 0.051 + offset], limit=200)[0]
        return num / (TAU * (1 - math.exp(-5)))

    means = {}
    for off in (0.0, 0.004, -0.003):
        k = K.render_thermal_kernel(t, r, CAL.replace(time_offset_s=off), tf, psf=False)
        means[off] = k.centroid[1]
        assert means[off] == pytest.approx(analytic_mean(off), rel=3e-3)
        # the same as shifting the stamps by hand
        ks = K.render_thermal_kernel(t + off, r, CAL, tf, psf=False)
        np.testing.assert_allclose(k.weights, ks.weights, atol=1e-6)
    # a later gyro clock (positive offset) → motion stops later in camera time → more blur
    assert means[0.004] > means[0.0] > means[-0.003]
    assert means[0.004] - means[0.0] > 0.5


def test_rolling_readout_shifts_per_row_kernels():
    # accelerating yaw: rows read earlier see a slower pan
    t, r = gyro_from(lambda s: (0.0, 2.0 * s, 0.0), t1=0.2)
    cal = CAL.replace(readout_s=0.015)
    tf = 0.15
    g = K.render_kernel_grid(t, r, cal, tf, (4, 1), psf=False)
    H = cal.height
    prev = -1.0
    for i in range(4):
        y = g.centers[i, 0, 0]
        t_row = tf - 0.015 * (1 - (y + 1) / H)
        assert g.times[i] == pytest.approx(t_row)
        assert t_row == pytest.approx(row_read_time(tf, y, cal.readout_s, cal.height))
        same = K.render_thermal_kernel(t, r, CAL, t_row, point=(g.centers[i, 0, 1], y), psf=False)
        np.testing.assert_allclose(g.kernels[i][0].weights, same.weights, atol=1e-6)
        # mean offset = f ∫ w(Δ) (ω(t_row)Δ − ½·2Δ²) dΔ / ∫ w ≈ f·(ω(t_row)·E[Δ] − E[Δ²])
        ux = g.kernels[i][0].centroid[1]
        assert ux > prev
        prev = ux
    w_top, w_bot = 2.0 * g.times[0], 2.0 * g.times[-1]
    ratio = g.kernels[-1][0].centroid[1] / g.kernels[0][0].centroid[1]
    assert ratio == pytest.approx((w_bot - 2 * TAU) / (w_top - 2 * TAU), rel=0.02)
    # the single-kernel API honours the readout too: the point's row sets the window end
    k = K.render_thermal_kernel(t, r, cal, tf, point=(10.0, 0.0), psf=False)
    k0 = K.render_thermal_kernel(t, r, CAL, tf - 0.015 * (1 - 1 / H), point=(10.0, 0.0), psf=False)
    np.testing.assert_array_equal(k.weights, k0.weights)


# ------------------------------------------------------------------------------------ PSF & grid
def test_optical_psf_eq19():
    s = CAL.psf_sigma_px                           # 0.45·10·1/0.6 µm / 17 µm ≈ 0.441 px
    assert s == pytest.approx(0.45 * 10 / 0.6 / 17)
    g = K.optical_psf(s)
    assert g.weights.shape == (5, 5) and g.origin == (2, 2)
    assert g.weights.sum() == pytest.approx(1.0, abs=1e-6)
    x = np.arange(-2, 3)
    row = g.weights.sum(axis=0)
    e = np.exp(-0.5 * (x / s) ** 2)
    np.testing.assert_allclose(row, e / e.sum(), rtol=1e-5)
    g2 = K.optical_psf(2.0)
    assert g2.weights.shape == (13, 13)
    var = (g2.weights.sum(axis=0) * (np.arange(13) - 6) ** 2).sum()
    assert var == pytest.approx(4.0, rel=0.015)    # sampled, truncated at 3σ
    assert K.optical_psf(0.0).weights.shape == (1, 1)
    # psf=True is the motion kernel convolved with the PSF
    t, r = gyro_from(lambda s_: (0.4, 0.7 * math.sin(50 * s_), 0.3))
    k0 = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=False)
    k1 = K.render_thermal_kernel(t, r, CAL, 0.0605, psf=True)
    from scipy.signal import convolve2d
    np.testing.assert_allclose(k1.weights, convolve2d(k0.weights, g.weights), atol=1e-6)
    assert k1.origin == (k0.origin[0] + 2, k0.origin[1] + 2)


def test_kernel_grid_layout_and_roll_variation():
    t, r = gyro_const((0, 0, 30 * DEG))
    g = K.render_kernel_grid(t, r, CAL, 0.0605, (6, 8), psf=False)
    assert g.grid == (6, 8) and len(g.kernels) == 6 and all(len(row) == 8 for row in g.kernels)
    assert g.image_shape == (480, 640)
    assert g.bounds[0, 0, 0] == 0 and g.bounds[-1, -1, 1] == 480 and g.bounds[-1, -1, 3] == 640
    np.testing.assert_array_equal(g.bounds[1:, :, 0], g.bounds[:-1, :, 1])
    np.testing.assert_allclose(g.centers[0, 0], (39.5, 39.5))
    # roll: blur grows with the distance from the principal point, tangential direction
    for i in range(6):
        for j in range(8):
            y, x = g.centers[i, j]
            k = g.kernels[i][j]
            uy, ux = k.centroid
            rad = np.hypot(x - CAL.cx, y - CAL.cy)
            assert np.hypot(ux, uy) == pytest.approx(rad * 30 * DEG * TAU * TRUNC_MEAN_5, rel=0.01)
            # u ⟂ (p − c): rotation about the optical axis
            assert abs(ux * (x - CAL.cx) + uy * (y - CAL.cy)) < 0.02 * rad * np.hypot(ux, uy) + 1e-9
    assert g.kernel_at(0, 0) is g.kernels[0][0] and g.kernel_at(479, 639) is g.kernels[5][7]
    assert g.max_extent_px == pytest.approx(max(k.extent_px for row in g.kernels for k in row))
    # photon grid: default exposure one frame period
    gp = K.render_kernel_grid(t, r, CAL, 0.0605, (2, 2), kind="photon", psf=False)
    assert gp.kind == "photon"
    kp = K.render_photon_kernel(t, r, CAL, 0.0605, 1 / CAL.frame_rate_hz, point=gp.centers[0, 0][::-1],
                                psf=False)
    np.testing.assert_array_equal(gp.kernels[0][0].weights, kp.weights)
    default = K.render_photon_kernel(t, r, CAL, 0.0605, point=gp.centers[0, 0][::-1], psf=False)
    np.testing.assert_array_equal(default.weights, kp.weights)


# --------------------------------------------------------------------------------- forward model
def test_blur_convention_with_a_delta_image():
    k = K.Kernel(np.array([[0.0, 0.1, 0.0], [0.2, 0.3, 0.0], [0.0, 0.0, 0.4]], np.float32), (1, 0))
    img = np.zeros((20, 30), np.float32)
    img[10, 12] = 1.0
    b = K.blur(img, k)
    assert b.dtype == np.float32
    # B(p) = Σ_u k(u) S(p − u) with S = δ(p − p0): B(p0 + u) = k(u) = weights[oy + u_y, ox + u_x]
    for iy in range(3):
        for ix in range(3):
            assert b[10 + iy - 1, 12 + ix - 0] == pytest.approx(k.weights[iy, ix])
    assert b.sum() == pytest.approx(1.0, abs=1e-6)


def test_blur_matches_scipy_with_replicate_border():
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1000, (60, 70)).astype(np.float32)
    w = rng.uniform(0, 1, (15, 23)).astype(np.float32)
    w /= w.sum()
    k = K.Kernel(w, (3, 17))
    b = K.blur(img, k)
    # Σ_u k(u) S(p − u) = convolution of S with k centred at the origin
    full = np.zeros((2 * 17 + 1, 2 * 17 + 1), np.float64)
    full[17 - 3:17 - 3 + 15, 17 - 17:17 - 17 + 23] = w
    ref = ndimage.convolve(img.astype(np.float64), full, mode="nearest")
    np.testing.assert_allclose(b, ref, rtol=1e-5, atol=1e-2)
    assert K.blur(img.astype(np.uint16), k).dtype == np.float32


def test_blur_varying_uniform_grid_equals_blur_and_cells_use_their_kernel():
    rng = np.random.default_rng(4)
    cal = SMALL
    img = cv2.GaussianBlur(rng.uniform(0, 1000, (240, 320)).astype(np.float32), (0, 0), 2.0)
    t, r = gyro_const((0.2, 0.5, 0.0))
    g = K.render_kernel_grid(t, r, cal, 0.0605, (3, 4))
    same = K.KernelGrid([[g.kernels[1][1]] * 4 for _ in range(3)], g.centers, g.bounds, g.times,
                        g.image_shape)
    one = K.blur(img, g.kernels[1][1])
    np.testing.assert_allclose(K.blur_varying(img, same), one, rtol=1e-5, atol=1e-2)
    t, r = gyro_const((0, 0, 60 * DEG))
    g = K.render_kernel_grid(t, r, cal, 0.0605, (3, 4))
    bv = K.blur_varying(img, g)
    # corners lie beyond the outer centres: one cell's blur alone
    assert bv[5, 5] == pytest.approx(K.blur(img, g.kernels[0][0])[5, 5], rel=1e-5)
    assert bv[-3, -4] == pytest.approx(K.blur(img, g.kernels[2][3])[-3, -4], rel=1e-5)
    # between two centres along x: linear blend of the two cells' blurs
    c1, c2 = g.centers[0, 1, 1], g.centers[0, 2, 1]
    x = int(c1 + 0.3 * (c2 - c1))
    lam = (x - c1) / (c2 - c1)
    b1, b2 = K.blur(img, g.kernels[0][1])[5, x], K.blur(img, g.kernels[0][2])[5, x]
    assert abs(b1 - b2) > 0.5                       # the two cells really differ there
    assert bv[5, x] == pytest.approx((1 - lam) * b1 + lam * b2, rel=1e-5)
    assert bv.dtype == np.float32


# --------------------------------------------------------------- fine-time signs and geometry
def _scene(shape=(240, 320), seed=0):
    rng = np.random.default_rng(seed)
    s = cv2.GaussianBlur(rng.normal(0, 1, shape).astype(np.float32), (0, 0), 2.0)
    s = (s - s.min()) / (s.max() - s.min()) * 600 + 200
    for _ in range(12):                                 # a few warm blobs/edges
        y, x = rng.integers(20, shape[0] - 20), rng.integers(20, shape[1] - 20)
        cv2.rectangle(s, (int(x), int(y)), (int(x) + 12, int(y) + 7), float(rng.uniform(300, 1200)), -1)
    return cv2.GaussianBlur(s, (0, 0), 1.0)


def fine_time_frame(scene, omega, cal, tk, m=5.0, h=25e-6):
    """Microbolometer frame at tk: Σ_s w(s) S_k(π(K Q(s) K⁻¹ p)), w ∝ exp(−(tk − s)/τ), 25 µs steps.

    Q(s) = R(tk)ᵀ R(s) from the analytic camera rate by backward midpoint steps (no gyro sampling).
    """
    Kc, Ki = cal.K, np.linalg.inv(cal.K)
    n = int(round(m * cal.tau_s / h))
    acc = np.zeros_like(scene, dtype=np.float64)
    Q = np.eye(3)
    wsum = 0.0
    for j in range(n + 1):
        s = tk - j * h
        w = math.exp(-(tk - s) / cal.tau_s) * (0.5 if j in (0, n) else 1.0)
        H = Kc @ Q @ Ki
        acc += w * cv2.warpPerspective(scene, H, scene.shape[::-1], borderMode=cv2.BORDER_REPLICATE,
                                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        wsum += w
        Q = Q @ so3_exp(-np.asarray(omega(s - h / 2)) * h)
    return (acc / wsum).astype(np.float32)


# name: (camera rate ω(s), point, max residual RMS / contrast); 0.03 % is reached for a pure pan.
# Under roll the blur varies across the compared patch, hence the looser bounds there.
MOTIONS = {
    "yaw": (lambda s: (0.0, 60 * DEG, 0.0), None, 0.002),
    "pitch": (lambda s: (-45 * DEG, 0.0, 0.0), None, 0.002),
    "roll": (lambda s: (0.0, 0.0, 80 * DEG), (260.0, 40.0), 0.006),
    "mixed": (lambda s: (30 * DEG * math.sin(30 * s), -50 * DEG + 400 * DEG * s, 60 * DEG * math.cos(20 * s)),
              (90.0, 170.0), 0.003),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(MOTIONS))
def test_fine_time_simulation_matches_kernel_blur(name):
    omega, point, limit = MOTIONS[name]
    cal = SMALL
    tk = 0.0605
    scene = _scene()
    truth = fine_time_frame(scene, omega, cal, tk)
    t, r = gyro_from(omega)
    k = K.render_thermal_kernel(t, r, cal, tk, point=point, psf=False)
    model = K.blur(scene, k)
    x, y = point if point is not None else (cal.cx, cal.cy)
    half = 10 if name in ("roll", "mixed") else 80        # blur varies across the frame under roll
    sl = (slice(int(y) - half, int(y) + half), slice(int(x) - half, int(x) + half))
    contrast = np.percentile(scene, 99) - np.percentile(scene, 1)
    rms = float(np.sqrt(np.mean((model[sl] - truth[sl]) ** 2)))
    blur_rms = float(np.sqrt(np.mean((scene[sl] - truth[sl]) ** 2)))
    flipped = K.Kernel(np.ascontiguousarray(k.weights[::-1, ::-1]),
                       (k.weights.shape[0] - 1 - k.origin[0], k.weights.shape[1] - 1 - k.origin[1]))
    rms_flipped = float(np.sqrt(np.mean((K.blur(scene, flipped)[sl] - truth[sl]) ** 2)))
    assert k.extent_px > 4                          # a real blur, ≥ 4 px
    assert rms < limit * contrast, (rms, contrast)
    assert blur_rms > 5 * rms                       # the blur itself is far above the residual
    assert rms_flipped > 5 * rms                    # and the wrong sign would be seen


@pytest.mark.slow
def test_fine_time_roll_whole_frame_needs_the_grid():
    omega = lambda s: (0.0, 0.0, 120 * DEG)        # noqa: E731
    cal = SMALL
    tk = 0.0605
    scene = _scene(seed=2)
    truth = fine_time_frame(scene, omega, cal, tk)
    t, r = gyro_from(omega)
    g = K.render_kernel_grid(t, r, cal, tk, (6, 8), psf=False)
    single = K.blur(scene, K.render_thermal_kernel(t, r, cal, tk, psf=False))
    varying = K.blur_varying(scene, g)
    inner = (slice(12, -12), slice(12, -12))
    contrast = np.percentile(scene, 99) - np.percentile(scene, 1)
    rms_v = float(np.sqrt(np.mean((varying[inner] - truth[inner]) ** 2)))
    rms_s = float(np.sqrt(np.mean((single[inner] - truth[inner]) ** 2)))
    assert rms_v < 0.005 * contrast                # measured 0.26 %
    assert rms_s > 10 * rms_v                      # one kernel for the frame: 6.9 %


@pytest.mark.slow
def test_fine_time_with_full_gyro_calibration_chain():
    """Raw gyro = the true camera rate pushed back through bias, scale, rotation and clock offset."""
    omega, point, _ = MOTIONS["mixed"]
    cal = SMALL.replace(bias_rad_s=(0.02, -0.05, 0.01), scale=(1.05, 0.95, 1.1), time_offset_s=0.003
                        ).with_misalignment((0.3, -1.2, 0.6))
    Minv = np.linalg.inv(cal.gyro_to_camera_matrix)
    tg = np.arange(-0.01, 0.1, 1e-3)
    raw = np.array([Minv @ np.asarray(omega(s + cal.time_offset_s)) for s in tg]) + np.asarray(cal.bias_rad_s)
    tk = 0.0605
    scene = _scene(seed=1)
    truth = fine_time_frame(scene, omega, SMALL, tk)
    k = K.render_thermal_kernel(tg, raw.astype(np.float32), cal, tk, point=point, psf=False)
    sl = (slice(int(point[1]) - 10, int(point[1]) + 10), slice(int(point[0]) - 10, int(point[0]) + 10))
    contrast = np.percentile(scene, 99) - np.percentile(scene, 1)
    rms = float(np.sqrt(np.mean((K.blur(scene, k)[sl] - truth[sl]) ** 2)))
    assert rms < 0.002 * contrast                  # measured 0.04 %
    # ignoring the calibration is visibly wrong
    k_raw = K.render_thermal_kernel(tg, raw.astype(np.float32), SMALL, tk, point=point, psf=False)
    assert float(np.sqrt(np.mean((K.blur(scene, k_raw)[sl] - truth[sl]) ** 2))) > 0.02 * contrast


# ----------------------------------------------------------------------------------- real gyro
def _betaflight(path):
    d = np.loadtxt(path, delimiter=",", skiprows=1, usecols=(0, 1, 2, 3))
    dt = np.diff(d[:, 0])
    ok = (dt > 400) & (dt < 600)
    start = int(np.argmax(ok))                      # junk rows have their own time base
    d = d[start:]
    return (d[:, 0] - d[0, 0]) * 1e-6, np.radians(d[:, 1:4]).astype(np.float32)


def test_real_gyro_log_kernels(shared_data, require):
    csv = shared_data / "gyro" / "betaflight_smooth_2khz.csv"
    require(csv.exists(), f"real gyro log {csv}")
    t, r = _betaflight(csv)
    assert np.all(np.diff(t) > 0) and np.median(np.diff(t)) == pytest.approx(5e-4, rel=0.02)
    # flight controller (x fwd, y right, z down) → camera looking forward (x right, y down, z fwd)
    R = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    cal = CAL.replace(R_cam_gyro=tuple(map(tuple, R)), rate_hz=2000.0)
    rng = np.random.default_rng(5)
    extents = []
    for tf in rng.uniform(1.0, t[-1] - 1.0, 8):
        k = K.render_thermal_kernel(t, r, cal, tf)
        ref = render_thermal_kernel_reference(t, r, cal, tf)
        assert k.weights.shape == ref.weights.shape
        np.testing.assert_allclose(k.weights, ref.weights, atol=1e-5)
        assert k.n_samples == np.count_nonzero((t > tf - 5 * TAU) & (t <= tf)) >= 76   # 40 ms at 2 kHz
        assert k.coverage == 1.0
        assert k.weights.sum() == pytest.approx(1.0, abs=1e-5)
        # centroid ≈ first-order mean rotation: f·E_w[∫ω] with ω_y ↔ +x, ω_x ↔ −y
        path = K.render_path(t, r, cal, tf)
        assert np.abs(np.diff(path.u, axis=0)).max() < 0.5
        np.testing.assert_allclose(k.centroid[::-1], path.w @ path.u, atol=2e-3)
        extents.append(k.extent_px)
    assert max(extents) > 3                          # real flight: several pixels of blur


# ---------------------------------------------------------------------------------- validation
def test_bad_inputs_raise_clear_errors():
    t, r = gyro_const((0.1, 0.2, 0.3))
    with pytest.raises(ThermodError, match="gyro_rate.*shape"):
        K.render_thermal_kernel(t, r[:, :2], CAL, 0.05)
    with pytest.raises(ThermodError, match="gyro_rate.*samples"):
        K.render_thermal_kernel(t, r[:-1], CAL, 0.05)
    with pytest.raises(ThermodError, match="gyro_t.*1-D"):
        K.render_thermal_kernel(t[:, None], r, CAL, 0.05)
    with pytest.raises(ThermodError, match="gyro_t: no gyro samples"):
        K.render_thermal_kernel(t[:0], r[:0], CAL, 0.05)
    bad = r.copy()
    bad[45, 1] = np.nan
    with pytest.raises(ThermodError, match="gyro_rate.*NaN"):
        K.render_thermal_kernel(t, bad, CAL, 0.05)
    tb = t.copy()
    tb[40] = tb[41]
    with pytest.raises(ThermodError, match="gyro_t.*increasing"):
        K.render_thermal_kernel(tb, r, CAL, 0.05)
    with pytest.raises(ValueError, match="t_frame"):
        K.render_thermal_kernel(t, r, CAL, float("nan"))
    with pytest.raises(ThermodError, match="point"):
        K.render_thermal_kernel(t, r, CAL, 0.05, point=(1.0,))
    with pytest.raises(ThermodError, match="tau_s"):
        K.render_thermal_kernel(t, r, CAL.replace(tau_s=0.0), 0.05)
    with pytest.raises(ThermodError, match="exposure_s"):
        K.render_photon_kernel(t, r, CAL, 0.05, -1.0)
    with pytest.raises(ThermodError, match="grid"):
        K.render_kernel_grid(t, r, CAL, 0.05, (0, 3))
    with pytest.raises(ThermodError, match="kind"):
        K.render_kernel_grid(t, r, CAL, 0.05, (2, 3), kind="ccd")
    with pytest.raises(ThermodError, match="calib"):
        K.render_thermal_kernel(t, r, {"tau_s": 0.008}, 0.05)
    with pytest.raises(ThermodError, match="image"):
        K.blur(np.zeros((4, 4, 3)), K.optical_psf(1.0))
    with pytest.raises(ThermodError, match="grid"):
        g = K.render_kernel_grid(t, r, SMALL, 0.05, (2, 2))
        K.blur_varying(np.zeros((100, 100), np.float32), g)
    # degrees fed as rad/s: a clear error, not a hang or a 10⁵-px array
    with pytest.raises(ThermodError, match="gyro"):
        K.render_thermal_kernel(*gyro_const((0, 3000.0, 0)), CAL, 0.05)


def test_kernel_construction_is_checked():
    k = K.Kernel(np.ones((2, 3)) / 6, (np.int64(1), 2.0))
    assert k.weights.dtype == np.float32 and k.origin == (1, 2) and type(k.origin[0]) is int
    assert k.extent_px == pytest.approx(math.hypot(1, 2))
    assert k.centroid == pytest.approx((-0.5, -1.0))
    with pytest.raises(ThermodError, match="Kernel.origin"):
        K.Kernel(np.ones((2, 3), np.float32), (2, 0))
    with pytest.raises(ThermodError, match="Kernel.weights"):
        K.Kernel(np.ones(3, np.float32), (0, 0))


def test_coverage_at_both_ends_and_without_samples():
    v = 30 * DEG
    t, r = gyro_const(yaw(v), t0=0.08, t1=0.2)       # gyro starts 20 ms into the 40 ms window
    k = K.render_thermal_kernel(t, r, CAL, 0.1, psf=False)
    assert k.coverage == pytest.approx((1 - math.exp(-20 / 8)) / (1 - math.exp(-5)), rel=1e-9)
    assert k.n_samples == 20
    # the rate is held before the first sample: same kernel as a gyro that had it all along
    # (up to the sub-step ripple: the held stretch is split differently)
    full = K.render_thermal_kernel(*gyro_const(yaw(v), t0=0.0, t1=0.2), CAL, 0.1, psf=False)
    np.testing.assert_allclose(k.weights, full.weights, atol=2e-4)
    assert k.centroid[1] == pytest.approx(full.centroid[1], rel=1e-5)
    assert full.coverage == 1.0
    # every sample after the window: rate held from the first one, nothing covered
    k0 = K.render_thermal_kernel(t, r, CAL, 0.05, psf=False)
    assert k0.coverage == 0.0 and k0.n_samples == 0
    assert k0.centroid[1] == pytest.approx(full.centroid[1], rel=1e-5)
    # a gyro that stopped long ago: held at the last sample
    k1 = K.render_thermal_kernel(t, r, CAL, 0.5, psf=False)
    assert k1.coverage == 0.0 and k1.centroid[1] == pytest.approx(full.centroid[1], rel=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["yaw", "mixed"])
def test_fine_time_on_a_real_thermal_frame(name, shared_data, require):
    png = shared_data / "thermal" / "H20N_DJI_0003_R.png"
    require(png.exists(), f"real thermal frame {png}")
    img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.dtype == np.uint16
    h, w = img.shape
    scene = img[h // 2 - 120:h // 2 + 120, w // 2 - 160:w // 2 + 160].astype(np.float32)  # raw counts
    omega, point, _ = MOTIONS[name]
    truth = fine_time_frame(scene, omega, SMALL, 0.0605)
    t, r = gyro_from(omega)
    k = K.render_thermal_kernel(t, r, SMALL, 0.0605, point=point, psf=False)
    x, y = point if point is not None else (SMALL.cx, SMALL.cy)
    half = 80 if point is None else 10
    sl = (slice(int(y) - half, int(y) + half), slice(int(x) - half, int(x) + half))
    contrast = np.percentile(scene, 99) - np.percentile(scene, 1)
    rms = float(np.sqrt(np.mean((K.blur(scene, k)[sl] - truth[sl]) ** 2)))
    blur_rms = float(np.sqrt(np.mean((scene[sl] - truth[sl]) ** 2)))
    assert rms < 0.001 * contrast                  # measured ≈ 0.02–0.03 %
    assert blur_rms > 50 * rms
