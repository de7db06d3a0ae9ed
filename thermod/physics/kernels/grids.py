"""How long before a frame its kernel reaches, and which kernel grid a rotation calls for.

`kernel_span_s`: the kernel of a frame whose last row is read at t_k covers (t_k − span, t_k], the
span m·τ for a thermal kernel (Eq. 18; m = 5 leaves 0.7 % of the weight out) or the exposure for a
photon one (Eq. 17), plus the rolling readout before the last row. Everything that cuts a gyro
window for a frame (the daemon, offline deblurring, the flight import, calibration) uses it, and
`has_hole` says whether the window's samples hold a hole (a step over `MAX_STEP_PERIODS` periods).

`grids_within`: the coarsest grid over which one kernel per cell stays within a tolerance of the
true kernel everywhere in the cell, from the rotational flow field (`grids_within`'s docstring).
"""

from __future__ import annotations

import numpy as np

from thermod.physics.calibration import Calibration
from thermod.physics.detector import default_photon_exposure_s

MAX_STEP_PERIODS = 4.0    # a step between gyro samples longer than this many periods is a hole


def has_hole(gyro_t: np.ndarray, rate_hz: float) -> bool:
    """Whether consecutive samples are further apart than `MAX_STEP_PERIODS` periods."""
    return len(gyro_t) > 1 and bool(np.max(np.diff(gyro_t)) > MAX_STEP_PERIODS / rate_hz)


def kernel_span_s(calib: Calibration, *, kind: str = "thermal", m: float = 5.0,
                  exposure_s: float | None = None) -> float:
    """Seconds before a frame's last-row read that its kernel needs: m·τ (thermal) or the exposure
    (photon; None: one frame period), plus the readout."""
    if kind == "photon":
        span = exposure_s or default_photon_exposure_s(calib.frame_rate_hz)
    else:
        span = m * calib.tau_s
    return float(span + calib.readout_s)


def coarser_grids(grid: tuple[int, int], aspect: float) -> list[tuple[int, int]]:
    """`grid` and the coarser near-square grids below it down to (1, 1), finest first
    (rows r, cols round(r · aspect) with aspect = W/H, never more than `grid`'s)."""
    rows, cols = grid
    out = [(rows, cols)]
    for r in range(rows - 1, 0, -1):
        g = (r, max(1, min(cols, round(r * aspect))))
        if g not in out:
            out.append(g)
    if (1, 1) not in out:
        out.append((1, 1))
    return out


def grids_within(gyro_t: np.ndarray, gyro_rate: np.ndarray, calib: Calibration, t_frame: float,
                 finest: tuple[int, int], tols_px: tuple[float, ...], *, kind: str = "thermal",
                 m: float = 5.0, exposure_s: float | None = None) -> tuple[tuple[int, int], ...]:
    """For each tolerance in `tols_px`, the coarsest kernel grid (rows, cols), at most `finest`, over
    which one kernel per cell is within it of the true kernel everywhere in its cell; (1, 1) =
    uniform blur.

    A camera rotating at ω moves the pixel at p (relative to the principal point, focal length f)
    with the rotational flow field. Against the kernel at a cell's centre, a pixel h away is
    displaced differently by

        roll:        ω_z · h                      (a rotation moves a pixel at radius r by ω_z·r)
        pan / tilt:  ω_⊥ · (2·r_max·h − h²) / f   (the 1 + r²/f² growth of the flow off-axis)

    per second, with ω_⊥ = √(ω_x² + ω_y²) and r_max the farthest corner's radius. The kernel's
    centroid and spread move by that rate times the kernel's effective duration t_eff (τ for the
    thermal kernel of Eq. 18, whose weights decay as e^(−s/τ); half the exposure for the photon box
    of Eq. 17). The rates are the kernel-weighted means of |ω_z| and ω_⊥ over the frame's window
    (calibrated camera frame). A cell's half-diagonal h must keep t_eff·(…) within the tolerance;
    grids are tried coarse to fine (1×1, 2×3, 3×4, … 6×8 on a 4:3 sensor).
    """
    t_cam, w = calib.gyro_to_camera(gyro_t, gyro_rate)
    t0 = t_frame - kernel_span_s(calib, kind=kind, m=m, exposure_s=exposure_s)
    sel = (t_cam > t0) & (t_cam <= t_frame)
    if not np.any(sel):
        return ((1, 1),) * len(tols_px)
    age = t_frame - t_cam[sel]
    if kind == "photon":
        t_eff = 0.5 * (exposure_s or default_photon_exposure_s(calib.frame_rate_hz))
        weights = np.ones_like(age)
    else:
        t_eff = calib.tau_s
        weights = np.exp(-age / calib.tau_s)
    weights /= weights.sum()
    roll = float(weights @ np.abs(w[sel, 2]))
    perp = float(weights @ np.hypot(w[sel, 0], w[sel, 1]))
    h_img, w_img = calib.height, calib.width
    f = 0.5 * (calib.fx + calib.fy)
    r_max = max(np.hypot(x - calib.cx, y - calib.cy) for x in (-0.5, w_img - 0.5)
                for y in (-0.5, h_img - 0.5))

    def deviation_px(rows: int, cols: int) -> float:
        h = 0.5 * np.hypot(h_img / rows, w_img / cols)
        return t_eff * (roll * h + perp * max(2 * r_max * h - h * h, 0.0) / f)

    grids = coarser_grids(tuple(finest), w_img / h_img)[::-1]      # coarse to fine
    deviations = [deviation_px(*g) for g in grids]
    return tuple(next((g for g, d in zip(grids, deviations, strict=True) if d <= tol), tuple(finest))
                 for tol in tols_px)
