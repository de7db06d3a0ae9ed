"""Camera intrinsics, SO(3) maps and the rotation-only homography (Eq. 16).

Conventions (docs/design.md §2): OpenCV camera frame (x right, y down, z forward);
R(t) maps camera vectors to world and dR/dt = R [ω]×, ω the camera-frame rate.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics K = [[fx,0,cx],[0,fy,cy],[0,0,1]] of a width × height image."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def K_inv(self) -> np.ndarray:
        return np.linalg.inv(self.K)

    @property
    def ifov_rad(self) -> float:
        """Angular size of one pixel at the centre (rad)."""
        return 1.0 / self.fx

    @classmethod
    def from_ifov(cls, width: int, height: int, ifov_rad: float) -> Intrinsics:
        """Square pixels, principal point at the image centre."""
        f = 1.0 / ifov_rad
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the same camera with the image resized by `factor`."""
        return Intrinsics(
            int(round(self.width * factor)), int(round(self.height * factor)),
            self.fx * factor, self.fy * factor,
            (self.cx + 0.5) * factor - 0.5, (self.cy + 0.5) * factor - 0.5,
        )


def skew(w: np.ndarray) -> np.ndarray:
    """[w]×, the cross-product matrix."""
    x, y, z = w
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


#: Below this θ² the Rodrigues coefficients come from their Taylor series (θ < 1e-4 rad).
_SERIES_THETA_SQ = 1e-8


def so3_exp_into(px: float, py: float, pz: float, out: np.ndarray) -> None:
    """Rodrigues exp([φ]×) of φ = (px, py, pz) rad into `out` [3, 3]: I + a[φ]× + b[φ]×².

    a = sin θ/θ and b = (1 − cos θ)/θ², b written as 2 sin²(θ/2)/θ² (no cancellation at small θ),
    both from their Taylor series below θ = 1e-4. The scalar core: plain `math`, callable from
    numba-jitted code after `jit_cores()`; `so3_exp_many` is its vector form.
    """
    th2 = px * px + py * py + pz * pz
    if th2 < _SERIES_THETA_SQ:
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        sh = math.sin(0.5 * th)
        a = math.sin(th) / th
        b = 2.0 * sh * sh / th2
    out[0, 0] = 1.0 - b * (py * py + pz * pz)
    out[0, 1] = -a * pz + b * px * py
    out[0, 2] = a * py + b * px * pz
    out[1, 0] = a * pz + b * px * py
    out[1, 1] = 1.0 - b * (px * px + pz * pz)
    out[1, 2] = -a * px + b * py * pz
    out[2, 0] = -a * py + b * px * pz
    out[2, 1] = a * px + b * py * pz
    out[2, 2] = 1.0 - b * (px * px + py * py)


def so3_exp_many(rotvecs) -> np.ndarray:
    """`so3_exp_into` vectorised: [n, 3] rotation vectors (rad) → [n, 3, 3] rotation matrices."""
    w = np.asarray(rotvecs, dtype=np.float64).reshape(-1, 3)
    px, py, pz = w[:, 0], w[:, 1], w[:, 2]
    th2 = px * px + py * py + pz * pz
    series = th2 < _SERIES_THETA_SQ
    th2_safe = np.where(series, 1.0, th2)
    th = np.sqrt(th2_safe)
    sh = np.sin(0.5 * th)
    a = np.where(series, 1.0 - th2 / 6.0, np.sin(th) / th)
    b = np.where(series, 0.5 - th2 / 24.0, 2.0 * sh * sh / th2_safe)
    R = np.empty((len(w), 3, 3))
    R[:, 0, 0] = 1.0 - b * (py * py + pz * pz)
    R[:, 0, 1] = -a * pz + b * px * py
    R[:, 0, 2] = a * py + b * px * pz
    R[:, 1, 0] = a * pz + b * px * py
    R[:, 1, 1] = 1.0 - b * (px * px + pz * pz)
    R[:, 1, 2] = -a * px + b * py * pz
    R[:, 2, 0] = -a * py + b * px * pz
    R[:, 2, 1] = a * px + b * py * pz
    R[:, 2, 2] = 1.0 - b * (px * px + py * py)
    return R


def so3_exp(rotvec) -> np.ndarray:
    """Rodrigues: rotation vector (rad) → 3×3 rotation matrix (`so3_exp_into`)."""
    w = np.asarray(rotvec, dtype=np.float64)
    if w.shape != (3,):
        raise ValueError(f"rotvec: expected 3 components, got shape {w.shape}")
    out = np.empty((3, 3))
    so3_exp_into(float(w[0]), float(w[1]), float(w[2]), out)
    return out


def so3_log(R: np.ndarray) -> np.ndarray:
    """3×3 rotation matrix → rotation vector (rad)."""
    R = np.asarray(R, dtype=np.float64)
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-8:
        return 0.5 * v
    if np.pi - th < 1e-6:  # near π: take the axis from the symmetric part
        M = (R + np.eye(3)) / 2.0
        axis = M[:, int(np.argmax(np.diag(M)))]
        return th * axis / np.linalg.norm(axis)
    return th / (2.0 * np.sin(th)) * v


def rotation_homography(K: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """H = K Q K⁻¹ (Eq. 16): maps pixel p of the view at t_k to where the same ray sat at t_i."""
    return K @ Q @ np.linalg.inv(K)


def apply_homography(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """π(H p) for an [N, 2] array of pixel coordinates."""
    pts = np.asarray(pts, dtype=np.float64)
    ph = np.c_[pts, np.ones(len(pts))] @ H.T
    return ph[:, :2] / ph[:, 2:3]


def trapezoid_step_into(R: np.ndarray, w0: np.ndarray, w1: np.ndarray, dt: float, E: np.ndarray,
                        out: np.ndarray) -> None:
    """One step of dR/dt = R [ω]× with ω linear from w0 to w1 over dt: out = R · exp([½(w0+w1) dt]×).

    Exact for a constant rate, second order for a linear one: the rate semantics every integrator
    shares (`integrate_rotations`, the kernel renderer, the simulator's trajectory). dt < 0 steps
    backward; E [3, 3] is scratch. Scalar core, numba-compatible like `so3_exp_into`.
    """
    h = 0.5 * dt
    so3_exp_into(h * (w0[0] + w1[0]), h * (w0[1] + w1[1]), h * (w0[2] + w1[2]), E)
    for r in range(3):
        for c in range(3):
            out[r, c] = R[r, 0] * E[0, c] + R[r, 1] * E[1, c] + R[r, 2] * E[2, c]


def _integrate_outward(t, omega, j, Q):
    """Q[i] from Q[j] by `trapezoid_step_into`: backward below j, forward above it."""
    E = np.empty((3, 3))
    for i in range(j - 1, -1, -1):
        trapezoid_step_into(Q[i + 1], omega[i + 1], omega[i], t[i] - t[i + 1], E, Q[i])
    for i in range(j + 1, t.shape[0]):
        trapezoid_step_into(Q[i - 1], omega[i - 1], omega[i], t[i] - t[i - 1], E, Q[i])


@functools.cache
def jit_cores():
    """Make the scalar cores callable from numba-jitted code; returns the jitted integrator.

    numba is imported here, on first use, so processes that never integrate a path (recording,
    watching) do not pay its start-up. Jitted modules call this once at import.
    """
    from numba import njit
    from numba.extending import register_jitable

    register_jitable(so3_exp_into)
    register_jitable(trapezoid_step_into)
    return njit(cache=True, nogil=True)(_integrate_outward)


def integrate_rotations(t: np.ndarray, omega: np.ndarray, t_ref: float) -> np.ndarray:
    """Q_i = R(t_ref)ᵀ R(t_i) for every sample time t_i, from camera-frame rates ω_i (rad/s).

    ω is taken as the instantaneous rate at t_i, piecewise linear between samples (so each
    interval rotates by exp([½(ω_i+ω_{i+1}) Δt]×), `trapezoid_step_into`); outside the samples it
    is held constant. Integrated outward from t_ref (Q = I there): Q_i = Q_{i+1} · exp([−ω̄ Δt]×)
    before it (docs/design.md §1). The one integrator: the renderers and the forward model use it or its
    step, and are tested against it.
    """
    t = np.ascontiguousarray(t, dtype=np.float64)
    omega = np.ascontiguousarray(omega, dtype=np.float64)
    n = len(t)
    Q = np.empty((n, 3, 3))
    if n == 0:
        return Q
    if omega.shape != (n, 3):
        raise ValueError(f"omega: expected shape ({n}, 3) to match t, got {omega.shape}")
    # the last sample at or before t_ref, rotated to t_ref with ω interpolated there (held outside)
    j = min(max(int(np.searchsorted(t, t_ref, side="right")) - 1, 0), n - 1)
    w_ref = np.array([np.interp(t_ref, t, omega[:, a]) for a in range(3)])
    E = np.empty((3, 3))
    trapezoid_step_into(np.eye(3), w_ref, omega[j], t[j] - t_ref, E, Q[j])
    jit_cores()(t, omega, j, Q)
    return Q
