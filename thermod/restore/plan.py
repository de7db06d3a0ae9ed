"""Kernel planning for one frame: which gyro window, which kernel grid, which kernel, which solver.

`render` turns the raw gyro samples around a frame into its blur kernel (Eq. 16–19) or a grid of
kernels, as `DeblurConfig` asks; `grid_needed` picks the coarsest grid the roll in the window calls
for; `make_deconvolver` builds the solver a worker runs. The daemon's pipeline and offline deblurring
(`thermod.batch`) plan frames through these functions only, so both restore a frame the same way.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from thermod.physics.calibration import Calibration
from thermod.physics.detector import default_photon_exposure_s
from thermod.restore.settings import DeblurConfig


def render(gyro_t: np.ndarray, gyro_rate: np.ndarray, calib: Calibration, t_frame: float,
           deblur: DeblurConfig):
    """The frame's blur kernel (or grid) from raw gyro samples, per the deblur settings.

    Returns ``(kernel_or_grid, info)`` with info = kernel_size, kernel_extent_px, coverage (the
    worst cell's for a grid) and n_samples.
    """
    from thermod.physics import kernels  # numba start-up is paid only by processes that deblur

    if deblur.mode == "adaptive":
        g = grid_needed(gyro_t, gyro_rate, calib, t_frame, deblur)
        deblur = dataclasses.replace(deblur, mode="uniform" if g == (1, 1) else "grid", grid=g)
    if deblur.mode == "grid":
        g = kernels.render_kernel_grid(gyro_t, gyro_rate, calib, t_frame, grid=deblur.grid,
                                       kind=deblur.kernel, psf=deblur.psf, m=deblur.m,
                                       exposure_s=deblur.exposure_s)
        cells = [k for row in g.kernels for k in row]
        # the shape the grid travels in (`wire.pack_kernel`): the largest cell's when they share an
        # origin, larger when they do not (a frame reported [95, 15] for a [.., 95, 22] kernel message)
        info = dict(kernel_size=g.common_frame[1],
                    kernel_extent_px=float(g.max_extent_px), coverage=float(g.coverage),
                    n_samples=int(min(k.n_samples for k in cells)))
        return g, info
    if deblur.kernel == "photon":
        exposure = deblur.exposure_s or default_photon_exposure_s(calib.frame_rate_hz)
        k = kernels.render_photon_kernel(gyro_t, gyro_rate, calib, t_frame, exposure, psf=deblur.psf)
    else:
        k = kernels.render_thermal_kernel(gyro_t, gyro_rate, calib, t_frame, m=deblur.m, psf=deblur.psf)
    info = dict(kernel_size=tuple(int(s) for s in k.weights.shape), kernel_extent_px=float(k.extent_px),
                coverage=float(k.coverage), n_samples=int(k.n_samples))
    return k, info


def grid_needed(gyro_t: np.ndarray, gyro_rate: np.ndarray, calib: Calibration, t_frame: float,
                deblur: DeblurConfig) -> tuple[int, int]:
    """The coarsest kernel grid (rows, cols) over which one kernel per cell is within
    ``deblur.grid_tol_px`` of the true kernel everywhere in its cell (`grids_within`)."""
    return grids_within(gyro_t, gyro_rate, calib, t_frame, deblur, (deblur.grid_tol_px,))[0]


def grids_within(gyro_t: np.ndarray, gyro_rate: np.ndarray, calib: Calibration, t_frame: float,
                 deblur: DeblurConfig, tols_px: tuple[float, ...]) -> tuple[tuple[int, int], ...]:
    """For each tolerance in `tols_px`, the coarsest kernel grid (rows, cols) over which one kernel
    per cell is within it of the true kernel everywhere in its cell; (1, 1) = uniform blur.

    ``mode = "uniform"`` → (1, 1); ``"grid"`` → ``deblur.grid``; ``"adaptive"`` decides from the
    gyro. Physics: a camera rotating at ω moves the pixel at p (relative to the principal point,
    focal length f) with the flow  ṗ = ω_z·(p rotated 90°) + f·(ω_x, ω_y)-terms·(1 + |p|²/f²)  (the
    rotational flow field). Against the kernel at a cell's centre, a pixel h away is displaced
    differently by

        roll:        ω_z · h                      (a rotation moves a pixel at radius r by ω_z·r)
        pan / tilt:  ω_⊥ · (2·r_max·h − h²) / f   (the 1 + r²/f² growth of the flow off-axis)

    per second, with ω_⊥ = √(ω_x² + ω_y²) and r_max the farthest corner's radius. The kernel's
    centroid and spread move by that rate times the kernel's effective duration t_eff (τ for the
    thermal kernel of Eq. 18, whose weights decay as e^(−s/τ); half the exposure for the photon box
    of Eq. 17). The rates are the kernel-weighted means of |ω_z| and ω_⊥ over the frame's window
    (calibrated camera frame). A cell's half-diagonal h must keep t_eff·(…) within the tolerance;
    grids are tried coarse to fine (1×1, 2×3, 3×4, … 6×8 on a 4:3 sensor) up to ``deblur.grid``.
    """
    if deblur.mode == "uniform":
        return ((1, 1),) * len(tols_px)
    if deblur.mode == "grid":
        return (tuple(deblur.grid),) * len(tols_px)
    t_cam, w = calib.gyro_to_camera(gyro_t, gyro_rate)
    t0, t1 = kernel_window(calib, deblur, t_frame)
    sel = (t_cam > t0) & (t_cam <= t1)
    if not np.any(sel):
        return ((1, 1),) * len(tols_px)
    age = t_frame - t_cam[sel]
    if deblur.kernel == "photon":
        t_eff = 0.5 * (deblur.exposure_s or default_photon_exposure_s(calib.frame_rate_hz))
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

    grids = coarser_grids(tuple(deblur.grid), w_img / h_img)[::-1]      # coarse to fine
    deviations = [deviation_px(*g) for g in grids]
    return tuple(next((g for g, d in zip(grids, deviations, strict=True) if d <= tol), tuple(deblur.grid))
                 for tol in tols_px)


def solved_grid(deconv, kernel) -> tuple[int, int]:
    """The kernel grid a frame was solved with: (1, 1) for one kernel, and also for a grid over which
    the deconvolver took its uniform shortcut (``last_cells == 1``: every cell's kernel within its
    tolerance of the central one). The frame's header says so, and the governor books the solve's cost
    under one cell — under the grid's key it would make the grid look as cheap as a uniform solve."""
    if not hasattr(kernel, "kernels"):
        return (1, 1)
    return (1, 1) if getattr(deconv, "last_cells", 0) == 1 else tuple(kernel.grid)


def kernel_window(calib: Calibration, deblur: DeblurConfig, t_frame: float) -> tuple[float, float]:
    """Camera-clock span the kernel of a frame read at t_frame needs: (t_k − m·τ − readout, t_k]."""
    if deblur.kernel == "photon":
        span = deblur.exposure_s or default_photon_exposure_s(calib.frame_rate_hz)
    else:
        span = deblur.m * calib.tau_s
    return t_frame - span - calib.readout_s, t_frame


def make_deconvolver(deblur: DeblurConfig):
    from thermod.physics.deconv import Deconvolver
    # live kernels never repeat: an OTF cache would only hold ~3 MB per entry of dead weight
    # realtime: an FFT size first seen mid-stream is estimated, not measured (a measured plan would
    # stall the queue ~0.7 s on a machine without wisdom); warmup() measures the common sizes first.
    iterations = deblur.kf_iterations if deblur.method == "kf" else None
    return Deconvolver(method=deblur.method, alpha=deblur.alpha, lam=deblur.lam, cache_size=1, realtime=True,
                       iterations=iterations)


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
