"""Moving warm bodies: objects that move in the world, so two frames disagree where they are.

Everything else the simulator renders is a static scene seen by a rotating (and, with parallax,
translating) camera. A `HotObject` is a disc `delta_k` K warmer than whatever it covers, moving at
constant angular velocity: its centre's world direction at absolute time t is K⁻¹ (p0 + v (t − t_ref), 1)
in the world frame (= the camera at the first frame, `thermod.sim.motion.Trajectory`), i.e. p0 is its
pixel position in the first frame and v (px/s) its image velocity as the first frame's camera sees it.
A view at orientation R (camera → world) sees it at π(K Rᵀ d(t)). The disc is drawn with a one-pixel
linear edge (area-sampled to first order) and adds to the view; the fine-time renderer
(`thermod.sim.detector.render(movers=…)`) draws it into every fine step and into the sharp truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from thermod.errors import ThermodError
from thermod.sim.scenes import COUNTS_PER_K


@dataclass(frozen=True)
class HotObject:
    """A warm disc: first-frame pixel position `p0` (x, y), image velocity `v_px_s` (vx, vy) px/s,
    `radius_px` and temperature step `delta_k` (K, negative: a cold body); `t_ref` the first frame's
    time (set by the renderer when None)."""

    p0: tuple[float, float]
    v_px_s: tuple[float, float]
    radius_px: float = 12.0
    delta_k: float = 5.0
    t_ref: float | None = None

    def __post_init__(self):
        vals = (*self.p0, *self.v_px_s, self.radius_px, self.delta_k)
        if len(self.p0) != 2 or len(self.v_px_s) != 2 or not all(math.isfinite(float(v)) for v in vals):
            raise ThermodError(f"HotObject: expected finite p0 (x, y), v_px_s (vx, vy), radius and delta; "
                               f"got {self}")
        if not 0.5 <= self.radius_px <= 1000:
            raise ThermodError(f"HotObject: radius_px {self.radius_px} outside [0.5, 1000]")

    def at(self, t_ref: float) -> HotObject:
        return HotObject(self.p0, self.v_px_s, self.radius_px, self.delta_k, float(t_ref))

    @property
    def speed_px_s(self) -> float:
        return math.hypot(*self.v_px_s)

    def direction(self, t: float) -> np.ndarray:
        """World direction (not normalised, z = 1 at the first frame) of the centre at time t."""
        dt = float(t) - (self.t_ref or 0.0)
        return np.array([self.p0[0] + self.v_px_s[0] * dt, self.p0[1] + self.v_px_s[1] * dt, 1.0])

    def centre_px(self, R: np.ndarray, K: np.ndarray, t: float) -> tuple[float, float] | None:
        """The centre in the view at orientation R (camera → world) and time t, or None behind it."""
        h = K @ R.T @ np.linalg.solve(K, self.direction(t))
        if h[2] <= 1e-9:
            return None
        return float(h[0] / h[2]), float(h[1] / h[2])

    def draw(self, view: np.ndarray, R: np.ndarray, K: np.ndarray, t: float) -> np.ndarray:
        """`view` (counts) with the disc added in place at time t seen at orientation R; returns it."""
        c = self.centre_px(R, K, t)
        if c is None:
            return view
        H, W = view.shape
        r = self.radius_px
        x0, x1 = max(int(math.floor(c[0] - r - 1)), 0), min(int(math.ceil(c[0] + r + 2)), W)
        y0, y1 = max(int(math.floor(c[1] - r - 1)), 0), min(int(math.ceil(c[1] + r + 2)), H)
        if x0 >= x1 or y0 >= y1:
            return view
        yy, xx = np.mgrid[y0:y1, x0:x1]
        d = np.hypot(xx - c[0], yy - c[1])
        cover = np.clip(r + 0.5 - d, 0.0, 1.0)
        view[y0:y1, x0:x1] += (cover * (self.delta_k * COUNTS_PER_K)).astype(view.dtype)
        return view


def draw_all(movers, view: np.ndarray, R: np.ndarray, K: np.ndarray, t: float) -> np.ndarray:
    """Every mover drawn into a copy of `view` (the canvas crops are shared, so never in place)."""
    if not movers:
        return view
    out = np.array(view, np.float32, copy=True)
    for m in movers:
        m.draw(out, R, K, t)
    return out


def max_speed_px_s(movers) -> float:
    return max((m.speed_px_s for m in movers or ()), default=0.0)
