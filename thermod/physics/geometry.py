"""Camera intrinsics, SO(3) maps and the rotation-only homography (Eq. 16).

Conventions (DESIGN.md §2): OpenCV camera frame (x right, y down, z forward);
R(t) maps camera vectors to world and dR/dt = R [ω]×, ω the camera-frame rate.
"""

from __future__ import annotations

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


def so3_exp(rotvec) -> np.ndarray:
    """Rodrigues: rotation vector (rad) → 3×3 rotation matrix."""
    w = np.asarray(rotvec, dtype=np.float64)
    th = float(np.linalg.norm(w))
    W = skew(w)
    if th < 1e-8:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + (np.sin(th) / th) * W + ((1.0 - np.cos(th)) / th**2) * (W @ W)


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


def integrate_rotations(t: np.ndarray, omega: np.ndarray, t_ref: float) -> np.ndarray:
    """Q_i = R(t_ref)ᵀ R(t_i) for every sample time t_i, from camera-frame rates ω_i (rad/s).

    ω is taken as the instantaneous rate at t_i, piecewise linear between samples (so each
    interval rotates by exp([½(ω_i+ω_{i+1}) Δt]×)); outside the samples it is held constant.
    Integrated backward from t_ref (Q = I there): Q_i = Q_{i+1} · exp([−ω̄ Δt]×) (DESIGN.md §1).
    This is the reference semantics every renderer (numba or not) must match.
    """
    t = np.asarray(t, dtype=np.float64)
    omega = np.asarray(omega, dtype=np.float64)
    n = len(t)
    Q = np.empty((n, 3, 3))
    if n == 0:
        return Q
    # Rotation at t_ref relative to the last sample, with ω linearly interpolated at t_ref.
    j = int(np.searchsorted(t, t_ref, side="right")) - 1   # last sample at or before t_ref
    j = min(max(j, 0), n - 1)

    def w_at(tq):
        if tq <= t[0]:
            return omega[0]
        if tq >= t[-1]:
            return omega[-1]
        return np.array([np.interp(tq, t, omega[:, a]) for a in range(3)])

    # Q_j = R(t_ref)ᵀ R(t_j): rotate from t_j to t_ref then invert.
    dt = t_ref - t[j]
    wbar = 0.5 * (omega[j] + w_at(t_ref))
    Q[j] = so3_exp(-wbar * dt)
    for i in range(j - 1, -1, -1):
        Q[i] = Q[i + 1] @ so3_exp(-0.5 * (omega[i] + omega[i + 1]) * (t[i + 1] - t[i]))
    for i in range(j + 1, n):  # samples after t_ref (rolling readout can need a few)
        Q[i] = Q[i - 1] @ so3_exp(0.5 * (omega[i] + omega[i - 1]) * (t[i] - t[i - 1]))
    return Q
