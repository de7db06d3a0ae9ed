"""Parallax: a near scene seen by a camera that translates — outside the rotation-only model.

Everything in thermod's forward model assumes a scene far away compared with the payload's
translation (docs/design.md §1): two views differ by the rotation homography of Eq. 16 alone. A
payload flying low over the ground breaks that: ground points move across the image by f·ρ·ΔT
(ρ = 1/distance along the ray, ΔT the translation across the ray), different for every row. The
simulator renders it so the discrepancy workflow can be tested on an effect it has no name for.

`NearGround(height_m, speed_m_s, seed)`: flat ground `height_m` below the camera's position at the
first frame (world +y, down; world = the camera at the first frame), so a ray of unit world direction
u hits it at distance height/u_y (u_y > 0; rays at or above the horizon see a far background, ρ = 0);
the camera translates with a seeded, zero-mean horizontal sway (world x and z, 0.3–2 Hz, `speed_m_s`
RMS per axis) and a third of it vertically, position T(t) = 0 at the first frame.

First-order parallax (|T| ≪ the distances): the pixel whose world ray is d sees the scene point in
direction d + |d| ρ(d) T, i.e. the rotation-only source direction moved by ρ T.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from thermod.errors import ThermodError

SWAY_HZ = (0.3, 2.0)
_AXIS_SHARE = np.array([1.0, 1.0 / 3.0, 1.0])          # world x (right), y (down), z (forward)


@dataclass(frozen=True)
class NearGround:
    height_m: float
    speed_m_s: float
    seed: int = 0
    t_ref: float = 0.0                 # absolute time of the first frame (T = 0 there)
    n_lines: int = 6

    def __post_init__(self):
        if not (math.isfinite(self.height_m) and self.height_m > 0):
            raise ThermodError(f"--effect parallax: height {self.height_m!r} m: expected > 0")
        if not (math.isfinite(self.speed_m_s) and self.speed_m_s >= 0):
            raise ThermodError(f"--effect parallax: speed {self.speed_m_s!r} m/s: expected ≥ 0")
        rng = np.random.default_rng([self.seed, 21])
        f = np.exp(rng.uniform(math.log(SWAY_HZ[0]), math.log(SWAY_HZ[1]), (self.n_lines, 3)))
        v = np.full((self.n_lines, 3), math.sqrt(2.0 / self.n_lines))      # unit RMS speed per axis
        object.__setattr__(self, "_f", f)
        object.__setattr__(self, "_v", v * self.speed_m_s * _AXIS_SHARE)
        object.__setattr__(self, "_ph", rng.uniform(0, 2 * math.pi, (self.n_lines, 3)))

    def position(self, t) -> np.ndarray:
        """T(t) [n, 3] (m, world frame) for absolute times t: ∫ v, zero at `t_ref`."""
        t = np.atleast_1d(np.asarray(t, float))[:, None, None]
        w = 2 * math.pi * self._f

        def p(tt):
            return (self._v / w * np.sin(w * tt + self._ph)).sum(axis=1)

        return p(t - self.t_ref) - p(np.zeros((1, 1, 1)))

    def max_shift_px(self, f_px: float, t0: float, t1: float) -> float:
        """An upper bound of the parallax shift (px) over [t0, t1] (ρ ≤ 1/height)."""
        T = self.position(np.linspace(t0, t1, 16))
        return float(f_px * np.linalg.norm(T, axis=1).max() / self.height_m) + 1.0

    def source_rays(self, rays_world: np.ndarray, t: float) -> np.ndarray:
        """The directions (world, not normalised) the rays `rays_world` [3, N] (each d = R K⁻¹ p, any
        length) see at absolute time t: d + |d| ρ(d/|d|) T(t), with |d| ρ(d/|d|) = max(d_y, 0)/height."""
        T = self.position(t)[0]
        g = np.maximum(rays_world[1], 0.0) / self.height_m
        return rays_world + g[None, :] * T[:, None]
