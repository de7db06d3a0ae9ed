"""Calibration → renderer parameters, input checks, and the window and sampling bounds of a kernel."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from thermod.physics.calibration import Calibration
from thermod.physics.detector import row_read_time
from thermod.physics.kernels.core import PathStatus
from thermod.physics.kernels.types import KernelError

#: Largest spacing between consecutive splats along the path (px); < 0.5 px avoids stepping (Eq. 12),
#: 0.25 keeps the bilinear-splat ripple along a fast path below ~2 %.
MAX_STEP_PX = 0.25
#: Refuse paths needing more nodes than this (a garbage rate, not a real motion).
MAX_NODES = 2_000_000


@dataclass(frozen=True)
class RendererParams:
    """The calibration as the renderer uses it, checked once (and cached per Calibration)."""

    M: np.ndarray        # ω_cam = M (ω_gyro − bias)
    bias: np.ndarray
    offset: float        # camera time = gyro time + offset
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    tau: float
    readout: float
    psf_sigma: float

    @functools.cached_property
    def camera(self) -> tuple:
        """(fx, fy, cx, cy) as the plain tuple the jitted core reads as a `Pinhole`."""
        return (self.fx, self.fy, self.cx, self.cy)

    @functools.cached_property
    def max_size_px(self) -> int:
        """Largest kernel side: a blur wider than twice the frame is no real motion (refused, not cropped)."""
        return 2 * max(self.width, self.height) + 64


def make_params(calib: Calibration) -> RendererParams:
    """Check the calibration fields the renderer needs and convert them (KernelError names the field)."""
    if not isinstance(calib, Calibration):
        raise KernelError(f"calib: expected a Calibration, got {type(calib).__name__}")
    M = np.ascontiguousarray(calib.gyro_to_camera_matrix, dtype=np.float64)
    bias = np.ascontiguousarray(np.asarray(calib.bias_rad_s, dtype=np.float64).ravel())
    if M.shape != (3, 3) or not np.isfinite(M).all():
        raise KernelError(f"calib.R_cam_gyro/scale: expected a finite 3×3 gyro→camera map, got {M}")
    if bias.shape != (3,) or not np.isfinite(bias).all():
        raise KernelError(f"calib.bias_rad_s: expected 3 finite values, got {calib.bias_rad_s!r}")
    for name in ("fx", "fy", "tau_s", "width", "height"):
        v = float(getattr(calib, name))
        if not (math.isfinite(v) and v > 0):
            raise KernelError(f"calib.{name}: expected a finite positive value, got {v!r}")
    for name in ("cx", "cy", "time_offset_s", "readout_s"):
        v = float(getattr(calib, name))
        if not math.isfinite(v) or (name == "readout_s" and v < 0):
            raise KernelError(f"calib.{name}: expected a finite value (≥ 0 for readout_s), got {v!r}")
    sigma = float(calib.psf_sigma_px)
    if not (math.isfinite(sigma) and sigma >= 0):
        raise KernelError(f"calib: optical PSF σ (Eq. 19) must be finite and ≥ 0, got {sigma!r} px "
                          "(check wavelength_um, f_number, psf_beta, pixel_pitch_um)")
    return RendererParams(M, bias, float(calib.time_offset_s), float(calib.fx), float(calib.fy),
                          float(calib.cx), float(calib.cy), int(calib.width), int(calib.height),
                          float(calib.tau_s), float(calib.readout_s), sigma)


@functools.lru_cache(maxsize=64)
def _params_cached(calib: Calibration) -> RendererParams:
    return make_params(calib)


def params(calib: Calibration) -> RendererParams:
    """`make_params`, cached for hashable calibrations."""
    try:
        return _params_cached(calib)
    except TypeError:   # unhashable fields (e.g. numpy arrays passed directly): no caching
        return make_params(calib)


def window(p: RendererParams, t_frame: float, y: float, length: float) -> tuple[float, float]:
    """(a, b]: the `length` s before the read time b of image row y (rolling readout)."""
    b = row_read_time(t_frame, y, p.readout, p.height)
    return b - length, b


def px_per_rad(p: RendererParams, x: float, y: float) -> float:
    """Upper bound on image speed per rad/s (px) at (x, y) and at the image corners: f·(1 + ρ²).

    The rotational motion field at normalised (x, y) is bounded by |ω|·(1 + x² + y²); the bound is
    taken over the whole frame (so every point of a frame gets the same sub-steps and a grid cell's
    kernel equals the single kernel rendered there), with a margin for rays drifting outward.
    """
    rx = max(abs(p.cx + 0.5), abs(p.width - 0.5 - p.cx), abs(x - p.cx)) / p.fx
    ry = max(abs(p.cy + 0.5), abs(p.height - 0.5 - p.cy), abs(y - p.cy)) / p.fy
    rho = math.sqrt(rx * rx + ry * ry) + 0.05
    return max(p.fx, p.fy) * (1.0 + rho * rho) * 1.05


_STATUS_MESSAGES = {
    PathStatus.TOO_MANY_NODES: "the motion needs more than {n} path nodes (rates of thousands of rad/s?): "
                               "check the gyro units/scale",
    PathStatus.BEHIND_CAMERA: "the camera turned more than 90° within the window: check the gyro units "
                              "(rad/s) and scale",
    PathStatus.TOO_LARGE: "the blur path spans more than {size} px: check the gyro units (rad/s) and scale",
    PathStatus.NONFINITE_TIMES: "gyro_t: non-finite sample times in the window",
    PathStatus.TIMES_NOT_INCREASING: "gyro_t: sample times must be strictly increasing",
    PathStatus.NONFINITE_RATES: "gyro_rate: NaN/inf rates in the window",
}


def raise_status(st: int, p: RendererParams, a: float, b: float, x: float, y: float):
    """Raise the KernelError a jitted renderer's status stands for."""
    msg = _STATUS_MESSAGES[PathStatus(st)].format(n=MAX_NODES, size=p.max_size_px)
    if not msg.startswith("gyro_"):
        msg = f"gyro_rate: at point ({x:.1f}, {y:.1f}), {msg}"
    raise KernelError(f"{msg} (window [{a:.6f}, {b:.6f}] s, camera clock)")


# ------------------------------------------------------------------------------------- validation
def check_gyro(gyro_t, gyro_rate) -> tuple[np.ndarray, np.ndarray]:
    """Shapes and dtypes (cheap); finiteness and ordering are checked on the window's samples only."""
    t = np.asarray(gyro_t)
    r = np.asarray(gyro_rate)
    if t.ndim != 1:
        raise KernelError(f"gyro_t: expected a 1-D array of sample times, got shape {t.shape}")
    if r.ndim != 2 or r.shape[1] != 3:
        raise KernelError(f"gyro_rate: expected shape [n, 3] (rad/s, gyro frame), got {r.shape}")
    if r.shape[0] != t.shape[0]:
        raise KernelError(f"gyro_rate: has {r.shape[0]} samples but gyro_t has {t.shape[0]}")
    if t.shape[0] == 0:
        raise KernelError("gyro_t: no gyro samples; a kernel needs at least one")
    if t.dtype != np.float64:
        if not (np.issubdtype(t.dtype, np.floating) or np.issubdtype(t.dtype, np.integer)):
            raise KernelError(f"gyro_t: expected float seconds, got dtype {t.dtype}")
        t = t.astype(np.float64)
    if r.dtype != np.float32 and r.dtype != np.float64:
        if not (np.issubdtype(r.dtype, np.floating) or np.issubdtype(r.dtype, np.integer)):
            raise KernelError(f"gyro_rate: expected float rad/s, got dtype {r.dtype}")
        r = r.astype(np.float64)
    return t, r


def check_scalar(name: str, v, positive: bool = False) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise KernelError(f"{name}: expected a number, got {v!r}") from None
    if not math.isfinite(f) or (positive and f <= 0):
        raise KernelError(f"{name}: expected a finite{' positive' if positive else ''} number, got {v!r}")
    return f


def check_point(point, p: RendererParams) -> tuple[float, float]:
    if point is None:
        return p.cx, p.cy
    try:
        x, y = (float(c) for c in point)
    except (TypeError, ValueError):
        raise KernelError(f"point: expected (x, y) pixel coordinates, got {point!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise KernelError(f"point: expected finite (x, y), got {point!r}")
    return x, y
