"""The public renderers: thermal (Eq. 18), photon (Eq. 17), grids, the path; the optical PSF (Eq. 19)."""

from __future__ import annotations

import functools
import math

import numpy as np

from thermod.physics.calibration import Calibration
from thermod.physics.detector import default_photon_exposure_s
from thermod.physics.kernels.core import (
    kernel_at,
    path_nodes,
    path_offsets,
    render_one,
)
from thermod.physics.kernels.params import (
    MAX_NODES,
    MAX_STEP_PX,
    RendererParams,
    check_gyro,
    check_point,
    check_scalar,
    params,
    px_per_rad,
    raise_status,
    window,
)
from thermod.physics.kernels.types import Kernel, KernelError, KernelGrid, KernelPath

_NO_PSF = np.ones(1)
_NO_PSF.setflags(write=False)   # read-only like the cached Gaussians: one numba specialisation


@functools.lru_cache(maxsize=32)
def _gauss_1d(sigma: float) -> np.ndarray:
    """Sampled, normalised Gaussian, radius ceil(3σ) (as cv2.getGaussianKernel samples it)."""
    if sigma < 1e-3:          # below a thousandth of a pixel the sampled Gaussian is a delta
        return _NO_PSF
    r = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    g.setflags(write=False)
    return g


def optical_psf(sigma_px: float) -> Kernel:
    """Optical PSF (Eq. 19) as a kernel: a sampled Gaussian of σ = sigma_px, radius ceil(3σ).

    σ = 0 gives a delta. `Calibration.psf_sigma_px` = 0.45·λ·F#/β / pitch.
    """
    s = check_scalar("sigma_px", sigma_px)
    if s < 0:
        raise KernelError(f"sigma_px: expected ≥ 0, got {sigma_px!r}")
    g = _gauss_1d(s)
    w = np.outer(g, g).astype(np.float32)
    r = g.shape[0] // 2
    return Kernel(w, (r, r), 1.0, 0)


def _psf_taps(p: RendererParams, psf: bool) -> np.ndarray:
    return _gauss_1d(p.psf_sigma) if psf and p.psf_sigma > 0 else _NO_PSF


def _path_args(p: RendererParams, a: float, b: float, box: bool, ppr: float) -> tuple[tuple, tuple]:
    """`PathWindow` and `PathSampling` as plain tuples for the jitted core (box windows ignore τ).

    Built in field order without the NamedTuple classes: this runs once per kernel, where a few
    µs matter; tests/physics/test_kernels.py checks the order against the classes.
    """
    win = (a, b, 1.0 if box else p.tau, box)          # a, b, ppr: floats; box: bool (one numba signature)
    smp = (ppr, MAX_STEP_PX, MAX_NODES, p.max_size_px)
    return win, smp


def _nodes_for(t, r, p: RendererParams, a: float, b: float, box: bool, ppr: float, x: float, y: float):
    win, smp = _path_args(p, a, b, box, ppr)
    times, Q, w, cov, ns, st = path_nodes(t, r, p.M, p.bias, p.offset, win, smp)
    if st:   # PathStatus.OK is 0
        raise_status(st, p, a, b, x, y)
    return times, Q, w, float(cov), int(ns)


def _kernel_from_nodes(Q, w, cov, n_samples, p: RendererParams, x: float, y: float, psf: bool,
                       a: float, b: float) -> Kernel:
    k, oy, ox, st = kernel_at(Q, w, (x, y), p.camera, p.max_size_px, _psf_taps(p, psf))
    if st:   # PathStatus.OK is 0
        raise_status(st, p, a, b, x, y)
    return Kernel(k, (int(oy), int(ox)), cov, n_samples)


def _render(t, r, p: RendererParams, a: float, b: float, box: bool, x: float, y: float, psf: bool) -> Kernel:
    win, smp = _path_args(p, a, b, box, px_per_rad(p, x, y))
    k, oy, ox, cov, ns, st = render_one(t, r, p.M, p.bias, p.offset, win, smp, (x, y), p.camera,
                                         _psf_taps(p, psf))
    if st:   # PathStatus.OK is 0
        raise_status(st, p, a, b, x, y)
    return Kernel(k, (int(oy), int(ox)), float(cov), int(ns))


def render_path(gyro_t, gyro_rate, calib: Calibration, t_frame: float, *, point=None, m: float = 5.0,
                exposure_s: float | None = None) -> KernelPath:
    """The sampled image path behind a kernel (before splatting and PSF), for plots and fits.

    Thermal weights over (t − mτ, t] by default; box weights over (t − exposure_s, t] when
    `exposure_s` is given. `t` is the read time of the point's row (rolling readout).
    """
    t, r = check_gyro(gyro_t, gyro_rate)
    p = params(calib)
    tf = check_scalar("t_frame", t_frame)
    x, y = check_point(point, p)
    box = exposure_s is not None
    length = check_scalar("exposure_s", exposure_s, True) if box else check_scalar("m", m, True) * p.tau
    a, b = window(p, tf, y, length)
    t, r = calib.condition_window(t, r, a, b)      # clock drift, DLPF, clipping (no-op when unset)
    times, Q, w, cov, ns = _nodes_for(t, r, p, a, b, box, px_per_rad(p, x, y), x, y)
    u, st = path_offsets(Q, (x, y), p.camera)
    if st:   # PathStatus.OK is 0
        raise_status(st, p, a, b, x, y)
    return KernelPath(times, u, w, cov, ns)


def render_thermal_kernel(gyro_t, gyro_rate, calib: Calibration, t_frame: float, *, point=None,
                          m: float = 5.0, psf: bool = True) -> Kernel:
    """Microbolometer blur kernel (Eq. 18) of the frame read at `t_frame`, at pixel `point`.

    Parameters
    ----------
    gyro_t, gyro_rate : RAW gyro samples, float [n] s (gyro clock) and [n, 3] rad/s (gyro frame);
        `calib` maps them to the camera (bias, scale, R_cam_gyro, time offset). Only the samples
        around the window are read, so a whole ring buffer may be passed.
    calib : Calibration (intrinsics, τ, optics, readout, gyro→camera).
    t_frame : frame time (s, camera clock): when its last row was read.
    point : (x, y) pixel; default the principal point. Under rolling readout the window ends at the
        read time of row y: t_frame − readout_s·(1 − (y+1)/H).
    m : window length in τ: (t − mτ, t]; m = 5 leaves 0.7 % of the weight out.
    psf : convolve with the optical PSF (Eq. 19, σ = calib.psf_sigma_px).

    Returns
    -------
    Kernel with weights ∝ ∫ exp(−(t − s)/τ) δ(u − u(s)) ds, normalised to 1; `coverage` < 1 when
    the gyro does not span the window (the rate is then held at the first/last sample).
    """
    t, r = check_gyro(gyro_t, gyro_rate)
    p = params(calib)
    tf = check_scalar("t_frame", t_frame)
    mm = check_scalar("m", m, True)
    x, y = check_point(point, p)
    a, b = window(p, tf, y, mm * p.tau)
    t, r = calib.condition_window(t, r, a, b)
    return _render(t, r, p, a, b, False, x, y, psf)


def render_photon_kernel(gyro_t, gyro_rate, calib: Calibration, t_frame: float,
                         exposure_s: float | None = None, *, point=None, psf: bool = True) -> Kernel:
    """Photon-detector (CCD/CMOS) blur kernel (Eq. 17): equal weights over (t − exposure_s, t].

    The baseline the thermal kernel must beat on a microbolometer; same path machinery, same
    arguments as `render_thermal_kernel`. exposure_s None: one frame period
    (`thermod.physics.detector.default_photon_exposure_s`).
    """
    t, r = check_gyro(gyro_t, gyro_rate)
    p = params(calib)
    tf = check_scalar("t_frame", t_frame)
    if exposure_s is None:
        exposure_s = default_photon_exposure_s(calib.frame_rate_hz)
    ex = check_scalar("exposure_s", exposure_s, True)
    x, y = check_point(point, p)
    a, b = window(p, tf, y, ex)
    t, r = calib.condition_window(t, r, a, b)
    return _render(t, r, p, a, b, True, x, y, psf)


def _grid_layout(h: int, w: int, rows: int, cols: int):
    """(centers, bounds) of a rows × cols grid, fresh copies of the cached layout."""
    centers, bounds = _grid_layout_cached(h, w, rows, cols)
    return centers.copy(), bounds.copy()


@functools.lru_cache(maxsize=64)
def _grid_layout_cached(h: int, w: int, rows: int, cols: int):
    ye = np.round(np.linspace(0, h, rows + 1)).astype(int)
    xe = np.round(np.linspace(0, w, cols + 1)).astype(int)
    centers = np.empty((rows, cols, 2))
    bounds = np.empty((rows, cols, 4), dtype=np.int64)
    for i in range(rows):
        for j in range(cols):
            centers[i, j] = ((ye[i] + ye[i + 1] - 1) / 2.0, (xe[j] + xe[j + 1] - 1) / 2.0)
            bounds[i, j] = (ye[i], ye[i + 1], xe[j], xe[j + 1])
    return centers, bounds


def render_kernel_grid(gyro_t, gyro_rate, calib: Calibration, t_frame: float, grid=(6, 8), *,
                       kind: str = "thermal", psf: bool = True, m: float = 5.0,
                       exposure_s: float | None = None) -> KernelGrid:
    """One kernel per cell centre of a rows × cols grid (roll makes the blur vary over the image).

    Under rolling readout the cells of a grid row centred on image row y use the read time
    t_frame − readout_s·(1 − (y+1)/H). `kind` = "thermal" (Eq. 18, window mτ) or "photon"
    (Eq. 17, `exposure_s`, default one frame period 1/frame_rate_hz). The rotations are integrated
    once per grid row and shared by its cells.
    """
    t, r = check_gyro(gyro_t, gyro_rate)
    p = params(calib)
    tf = check_scalar("t_frame", t_frame)
    try:
        rows, cols = (int(g) for g in grid)
    except (TypeError, ValueError):
        raise KernelError(f"grid: expected (rows, cols), got {grid!r}") from None
    if rows < 1 or cols < 1 or rows > p.height or cols > p.width:
        raise KernelError(f"grid: expected 1 ≤ rows ≤ {p.height} and 1 ≤ cols ≤ {p.width}, got {grid!r}")
    if kind == "thermal":
        box, length = False, check_scalar("m", m, True) * p.tau
    elif kind == "photon":
        box = True
        length = check_scalar("exposure_s", exposure_s if exposure_s is not None
                              else default_photon_exposure_s(calib.frame_rate_hz), True)
    else:
        raise KernelError(f"kind: expected 'thermal' or 'photon', got {kind!r}")
    centers, bounds = _grid_layout(p.height, p.width, rows, cols)
    ppr = px_per_rad(p, p.cx, p.cy)   # the frame-wide bound: same sub-steps as single kernels
    t, r = calib.condition_window(t, r, tf - p.readout - length, tf)
    kernels = []
    times = np.empty(rows)
    for i in range(rows):
        y = float(centers[i, 0, 0])
        a, b = window(p, tf, y, length)
        times[i] = b
        _, Q, w, cov, ns = _nodes_for(t, r, p, a, b, box, ppr, p.cx, y)
        kernels.append([_kernel_from_nodes(Q, w, cov, ns, p, float(centers[i, j, 1]), y, psf, a, b)
                        for j in range(cols)])
    return KernelGrid(kernels, centers, bounds, times, (p.height, p.width), kind)
