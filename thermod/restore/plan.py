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
from thermod.physics.kernels import grids as kernel_grids
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
    per cell is within it of the true kernel everywhere in its cell (`thermod.physics.kernels.grids`);
    ``mode = "uniform"`` → (1, 1), ``"grid"`` → ``deblur.grid``, ``"adaptive"`` decides from the gyro,
    up to ``deblur.grid``."""
    if deblur.mode == "uniform":
        return ((1, 1),) * len(tols_px)
    if deblur.mode == "grid":
        return (tuple(deblur.grid),) * len(tols_px)
    return kernel_grids.grids_within(gyro_t, gyro_rate, calib, t_frame, tuple(deblur.grid), tols_px,
                                     kind=deblur.kernel, m=deblur.m, exposure_s=deblur.exposure_s)


def solved_grid(deconv, kernel) -> tuple[int, int]:
    """The kernel grid a frame was solved with: (1, 1) for one kernel, and also for a grid over which
    the deconvolver took its uniform shortcut (``last_cells == 1``: every cell's kernel within its
    tolerance of the central one). The frame's header says so, and the governor books the solve's cost
    under one cell — under the grid's key it would make the grid look as cheap as a uniform solve."""
    if not hasattr(kernel, "kernels"):
        return (1, 1)
    return (1, 1) if getattr(deconv, "last_cells", 0) == 1 else tuple(kernel.grid)


def kernel_window(calib: Calibration, deblur: DeblurConfig, t_frame: float) -> tuple[float, float]:
    """Camera-clock span the kernel of a frame read at t_frame needs: (t_k − m·τ − readout, t_k]
    (`thermod.physics.kernels.grids.kernel_span_s`)."""
    span = kernel_grids.kernel_span_s(calib, kind=deblur.kernel, m=deblur.m, exposure_s=deblur.exposure_s)
    return t_frame - span, t_frame


def make_deconvolver(deblur: DeblurConfig, *, live: bool = True):
    """The one solver factory: a `Deconvolver` for the settings' method, α, λ and K&F steps.

    Per-frame kernels never repeat, so the OTF cache is tiny (live: one entry; offline: two).
    `live`: an FFT size first seen mid-stream is estimated, not measured (a measured plan would
    stall the queue ~0.7 s on a machine without wisdom; the daemon's warm-up measures the common
    sizes first); offline every plan is measured."""
    from thermod.physics.deconv import Deconvolver

    iterations = deblur.kf_iterations if deblur.method == "kf" else None
    return Deconvolver(method=deblur.method, alpha=deblur.alpha, lam=deblur.lam, cache_size=1 if live else 2,
                       realtime=live, iterations=iterations)
