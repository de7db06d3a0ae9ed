"""Detector physics: the microbolometer's first-order thermal low-pass and the photon detector.

Heat balance τ dΔT/dt + ΔT = R_th η Φ(t) (τ = C_th R_th). Discretised at step h:
backward Euler (Eq. 10) α = h/(τ+h), or exact for a piecewise-constant input α = 1 − exp(−h/τ).
Also the detector's timing: the rolling-readout row time and the photon baseline's exposure.
"""

from __future__ import annotations

import numpy as np

from thermod.errors import ThermodError

# A simulated camera's temporal noise unless told otherwise (K RMS): the "< 50 mK" NETD (f/1.0, 300 K
# scene) that the datasheets of common uncooled VOx cores give (FLIR Boson and Lepton 3.5, Teledyne
# FLIR, 2023). Noiseless frames make every static frame identical, which no camera does.
DEFAULT_NETD_K = 0.05


def iir_alpha(h, tau: float, exact: bool = True):
    """Blend weight α of B_k = (1 − α) B_{k−1} + α S_k over a step h (s); float, or array for array h.

    exact (default): α = 1 − exp(−h/τ), exact for an input constant over the step (Eq. 11);
    otherwise backward Euler α = h/(τ+h) (Eq. 10). τ ≤ 0 (no thermal lag) gives α = 1.
    """
    h = np.asarray(h, dtype=np.float64)
    if tau <= 0:
        a = np.ones_like(h)
    else:
        a = -np.expm1(-h / tau) if exact else h / (tau + h)
    return float(a) if a.ndim == 0 else a


def row_read_time(t_frame, row, readout_s: float, height: int):
    """Rolling readout: row `row` (may be fractional) of the frame read at t_frame is read at
    t_frame − readout_s·(1 − (row+1)/height); the last row at t_frame (docs/design.md §1).

    Broadcasts over NumPy arrays `t_frame` and `row`; plain arithmetic, so scalars stay cheap
    (the kernel renderer calls it once per kernel).
    """
    return t_frame - readout_s * (1.0 - (row + 1.0) / height)


def default_photon_exposure_s(frame_rate_hz: float) -> float:
    """Exposure of the photon-detector baseline (Eq. 2/17) when none is given: one frame period 1/f.

    A CCD/CMOS running at f frames/s integrates at most 1/f per frame; the baseline kernel takes
    that longest (100 % duty) exposure, the box that spans the same frame period a microbolometer's
    frame summarises. Shorter exposures are a choice of the camera and must be given explicitly.
    """
    f = float(frame_rate_hz)
    if not f > 0:
        raise ThermodError(f"frame_rate_hz: expected > 0, got {frame_rate_hz!r}")
    return 1.0 / f


def thermal_response(views: np.ndarray, h: float, tau: float, exact: bool = True,
                     initial: np.ndarray | None = None) -> np.ndarray:
    """Run the IIR of Eq. 10 over a time-ordered stack of sharp views [T, ...] (float32 out).

    Returns every B_k (Eq. 11: an exponential average of the past views). `initial` is the
    detector state before the first view (default: the first view, i.e. a settled detector).
    """
    views = np.asarray(views)
    a = np.float32(iir_alpha(h, tau, exact))
    out = np.empty(views.shape, dtype=np.float32)
    b = np.array(views[0] if initial is None else initial, dtype=np.float32)
    for k in range(len(views)):
        b = (1 - a) * b + a * views[k].astype(np.float32)
        out[k] = b
    return out


def thermal_weights(dt_before: np.ndarray, tau: float, durations: np.ndarray | None = None) -> np.ndarray:
    """Eq. 18 weights for samples taken dt_before seconds before the read: ∝ exp(−Δt/τ)·Δt_i, sum 1."""
    dt_before = np.asarray(dt_before, dtype=np.float64)
    w = np.exp(-dt_before / tau)
    if durations is not None:
        w = w * np.asarray(durations, dtype=np.float64)
    s = w.sum()
    return w / s if s > 0 else w


def photon_average(views: np.ndarray) -> np.ndarray:
    """Eq. 2: a photon detector's frame is the box average of the views over the exposure."""
    return np.asarray(views, dtype=np.float32).mean(axis=0)
