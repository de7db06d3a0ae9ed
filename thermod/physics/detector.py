"""Detector physics: the microbolometer's first-order thermal low-pass and the photon detector.

Heat balance τ dΔT/dt + ΔT = R_th η Φ(t) (τ = C_th R_th). Discretised at step h:
backward Euler (Eq. 10) α = h/(τ+h), or exact for a piecewise-constant input α = 1 − exp(−h/τ).
"""

from __future__ import annotations

import numpy as np


def iir_alpha(h: float, tau: float, exact: bool = True) -> float:
    """Blend weight α of B_k = (1 − α) B_{k−1} + α S_k (Eq. 10); exact form by default."""
    if tau <= 0:
        return 1.0
    return float(-np.expm1(-h / tau)) if exact else float(h / (tau + h))


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
