import math

import numpy as np
import pytest

from thermod.physics.geometry import (
    Intrinsics,
    apply_homography,
    integrate_rotations,
    rotation_homography,
    skew,
    so3_exp,
    so3_exp_many,
    so3_log,
)


def test_so3_exp_log_roundtrip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        axis = rng.normal(size=3)
        w = axis / np.linalg.norm(axis) * rng.uniform(1e-9, 3.1)  # angles below π: log is unique there
        R = so3_exp(w)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(so3_log(R), w, atol=1e-9)


def test_so3_log_near_pi():
    w = np.array([0.0, 0.0, np.pi - 1e-9])
    assert np.allclose(np.abs(so3_log(so3_exp(w))), np.abs(w), atol=1e-6)


def test_so3_exp_is_matrix_exponential_of_skew():
    from scipy.linalg import expm
    w = np.array([0.3, -0.2, 0.7])
    assert np.allclose(so3_exp(w), expm(skew(w)), atol=1e-12)


def test_integrate_constant_rate_matches_closed_form():
    # R(t) = exp(ω t)  ⇒  Q_i = R(t_ref)ᵀ R(t_i) = exp(−ω (t_ref − t_i))
    w = np.array([0.1, -0.4, 0.9])
    t = np.arange(0, 0.05, 0.001)
    Q = integrate_rotations(t, np.tile(w, (len(t), 1)), t_ref=0.0405)
    for i in (0, 10, 40, 49):
        assert np.allclose(Q[i], so3_exp(-w * (0.0405 - t[i])), atol=1e-12)


def test_integrate_linear_rate_is_second_order_accurate():
    # ω(t) = a t about z: angle(t) = a t²/2 exactly; trapezoid is exact for linear rates about one axis.
    a = 50.0
    t = np.arange(0, 0.04, 0.001)
    omega = np.c_[np.zeros_like(t), np.zeros_like(t), a * t]
    Q = integrate_rotations(t, omega, t_ref=t[-1])
    ang = so3_log(Q[0])[2]
    assert ang == pytest.approx(-a * t[-1] ** 2 / 2, rel=1e-9)


def test_yaw_moves_image_left_for_positive_y_rate():
    # Camera turning right (positive rate about y, down axis): scene content moves left in the image,
    # so the ray seen at the centre at t_ref was seen to the right of centre... earlier.
    K = Intrinsics.from_ifov(640, 480, np.radians(0.0391))
    Q = so3_exp([0.0, -np.radians(1.0), 0.0])  # R(t_ref)ᵀR(t_i) for an earlier t_i under +y rate
    p = np.array([[K.cx, K.cy]])
    q = apply_homography(rotation_homography(K.K, Q), p)
    assert q[0, 0] < K.cx - 20  # ~25.6 px at 1°
    assert q[0, 1] == pytest.approx(K.cy)


def test_intrinsics_scaled_keeps_angles():
    K = Intrinsics.from_ifov(640, 480, 0.001)
    Kh = K.scaled(0.5)
    assert (Kh.width, Kh.height) == (320, 240)
    assert Kh.fx == pytest.approx(500.0)
    # pixel centres map consistently: centre of the image stays the centre
    assert Kh.cx == pytest.approx((320 - 1) / 2)


@pytest.mark.parametrize("theta", [1e-12, 1e-9, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 0.1, 3.0])
def test_so3_exp_is_accurate_at_small_angles(theta):
    """exp([φ]×) = I + a[φ]× + b[φ]×², a = sin θ/θ, b = (1 − cos θ)/θ² = 2 sin²(θ/2)/θ². Written
    naively, 1 − cos θ cancels: b is off by ~1e-16/θ² relative (2e-4 at θ = 1e-6), which shows in
    the off-diagonal entries at 1e-10 relative."""
    axis = np.array([0.3, -0.5, 0.81])
    w = theta * axis / np.linalg.norm(axis)
    W = skew(w)
    a_true = math.sin(theta) / theta
    b_true = 2.0 * math.sin(theta / 2) ** 2 / theta**2 if theta > 1e-4 else 0.5 - theta**2 / 24
    expect = np.eye(3) + a_true * W + b_true * (W @ W)
    off = ~np.eye(3, dtype=bool)
    for R in (so3_exp(w), so3_exp_many(w[None])[0]):
        np.testing.assert_allclose(R[off], expect[off], rtol=1e-13, atol=0)
        np.testing.assert_allclose(np.diag(R), np.diag(expect), rtol=0, atol=3e-16)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)


def test_so3_exp_many_matches_the_scalar_core():
    rng = np.random.default_rng(3)
    w = rng.normal(size=(200, 3)) * np.exp(rng.uniform(-30, 1, (200, 1)))
    many = so3_exp_many(w)
    for i in range(len(w)):
        np.testing.assert_allclose(many[i], so3_exp(w[i]), rtol=0, atol=2e-16)


def test_integrate_rotations_holds_the_rate_outside_the_samples():
    t = np.array([0.0, 0.01, 0.02])
    omega = np.array([[0.0, 1.0, 0.0], [0.0, 2.0, 0.0], [0.0, 3.0, 0.0]])
    Q = integrate_rotations(t, omega, t_ref=0.05)   # after the last sample: ω = 3 held
    np.testing.assert_allclose(Q[2], so3_exp([0.0, -3.0 * 0.03, 0.0]), atol=1e-15)
    np.testing.assert_allclose(Q[1], Q[2] @ so3_exp([0.0, -2.5 * 0.01, 0.0]), atol=1e-15)
    Q = integrate_rotations(t, omega, t_ref=-0.02)  # before the first: ω = 1 held, samples ahead
    np.testing.assert_allclose(Q[0], so3_exp([0.0, 1.0 * 0.02, 0.0]), atol=1e-15)
    np.testing.assert_allclose(Q[2], Q[0] @ so3_exp([0.0, 1.5 * 0.01, 0.0]) @ so3_exp([0.0, 2.5 * 0.01, 0.0]),
                               atol=1e-15)
