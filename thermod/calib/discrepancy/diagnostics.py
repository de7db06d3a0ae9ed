"""Diagnostic panels: the residual against row, time, angular rate and acceleration, its spatial
spectrum and the kernel-centroid lag. Each effect names the panel that points at it."""

from __future__ import annotations

import math

import cv2
import numpy as np

from thermod.calib.discrepancy.data import Model, RecData
from thermod.calib.discrepancy.problem import Evaluation, Problem
from thermod.physics.calibration import Calibration

N_SPECTRUM_BINS = 10


def _frame_rates(d: RecData, calib: Calibration):
    """Camera-frame rate and angular acceleration at every motion frame's mid-read time."""
    t_cam, w = calib.gyro_to_camera(d.gyro_t, d.gyro_rate)
    tm = d.frame_t - 0.5 * calib.readout_s
    rate = np.stack([np.interp(tm, t_cam, w[:, a]) for a in range(3)], axis=1)
    h = 0.004
    acc = np.stack([(np.interp(tm + h, t_cam, w[:, a]) - np.interp(tm - h, t_cam, w[:, a])) / (2 * h)
                    for a in range(3)], axis=1)
    return rate, acc


def _centroid_lag(d: RecData, calib: Calibration, res: np.ndarray, pred: np.ndarray):
    """Per frame, the time lag (s) that best explains measured vs predicted as a shift along the image
    velocity: a first-order fit r ≈ −(∇P·v) δt (the kernel-centroid lag). NaN where the image is still."""
    tm = d.frame_t - 0.5 * calib.readout_s
    Hs = d.fm.homographies(calib, np.r_[tm - 0.001, tm + 0.001])
    n = len(tm)
    c = np.array([d.fm.intr.cx, d.fm.intr.cy, 1.0])
    out = np.full(n, np.nan)
    for k in range(n):
        p0 = Hs[k] @ c
        p1 = Hs[n + k] @ c
        v = (p1[:2] / p1[2] - p0[:2] / p0[2]) / 0.002   # where the centre ray's source moves (px/s)
        if np.hypot(*v) < 5.0:
            continue
        gx = cv2.Sobel(pred[k], cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(pred[k], cv2.CV_32F, 0, 1, ksize=3) / 8.0
        g = (gx * v[0] + gy * v[1]) * d.mask[k]
        den = float(np.sum(g.astype(np.float64) ** 2))
        if den > 0:
            out[k] = float(np.sum(g * res[k])) / den
    return out


def _radial_spectrum(r: np.ndarray) -> np.ndarray:
    """Mean power of the residual frames in radial frequency bins of 0.05 cycles/px."""
    P = np.mean(np.abs(np.fft.fft2(r)) ** 2, axis=0) / r[0].size
    h, w = P.shape
    fy, fx = np.meshgrid(np.fft.fftfreq(h), np.fft.fftfreq(w), indexing="ij")
    idx = np.digitize(np.hypot(fy, fx).ravel(), np.linspace(0, 0.5, N_SPECTRUM_BINS + 1)) - 1
    return np.array([P.ravel()[idx == i].mean() if np.any(idx == i) else 0.0 for i in range(N_SPECTRUM_BINS)])


def diagnostics(problem: Problem, model: Model, ev: Evaluation) -> dict:
    """Residual vs row, time, angular rate and acceleration, spectrum and centroid lag (all recordings)."""
    rows = rows_sig = spec = 0.0
    times, frame_rel, speeds, accs, lags = [], [], [], [], []
    spec_noise = 0.0
    for d, r, p in zip(problem.recs, ev.residuals, ev.predicted, strict=True):
        # relative to the motion signal, so scene content does not masquerade as structure
        sig = ((d.measured - d.static_mean) * d.mask).astype(np.float64) ** 2
        r2 = r.astype(np.float64) ** 2
        rows = rows + r2.sum(axis=(0, 2))
        rows_sig = rows_sig + sig.sum(axis=(0, 2))
        frame_rel.append(np.sqrt(r2.sum(axis=(1, 2)) / np.maximum(sig.sum(axis=(1, 2)), 1e-12)))
        times.append(d.frame_t - d.t_onset)
        rate, acc = _frame_rates(d, model.calib)
        speeds.append(np.degrees(np.linalg.norm(rate, axis=1)))
        accs.append(np.degrees(np.linalg.norm(acc, axis=1)))
        lags.append(_centroid_lag(d, model.calib, r, p))
        spec = spec + _radial_spectrum(r)
        spec_noise += d.noise_var * float(d.mask.mean())
    nrec = len(problem.recs)
    lag = np.concatenate(lags)
    dg = {
        "row_gap": np.sqrt(rows / np.maximum(rows_sig, 1e-12)),
        "noise_sd": math.sqrt(sum(d.noise_var for d in problem.recs) / nrec),
        "t": np.concatenate(times), "frame_gap": np.concatenate(frame_rel),
        "speed_deg_s": np.concatenate(speeds), "accel_deg_s2": np.concatenate(accs),
        "lag_s": lag, "lag_median_s": float(np.nanmedian(lag)) if np.any(np.isfinite(lag)) else float("nan"),
        "spectrum": spec / nrec, "spectrum_noise": spec_noise / nrec,
        "spectrum_freq": (np.arange(N_SPECTRUM_BINS) + 0.5) * 0.05,
    }
    dg.update(gyro_panels(problem, model, dg))
    return dg


# ------------------------------------------------------------------ gyro-side panels (issue 12)
def gyro_panels(problem: Problem, model: Model, dg: dict) -> dict:
    """Panels for the gyro-side effects, from the per-frame series above and the raw gyro.

    lag_trend (clock_drift): the centroid lag against time with its straight-line slope (a drifting
    clock makes the lag grow at ε s/s). lag_freq (gyro_lowpass): the lag against each frame's motion
    frequency |dω/dt| / (2π|ω|) (a pure offset is flat; a low-pass lags more, and attenuates, as the
    frequency nears its cutoff). clip (gyro_saturation): the raw |rate| distribution near its top
    (a pile-up at the range) and which frames' detector window (5τ) holds clipped samples.
    """
    from thermod.physics.gyro_effects import clipped_runs, detect_clip_level

    t, lag = np.asarray(dg["t"], float), np.asarray(dg["lag_s"], float)
    ok = np.isfinite(lag)
    slope = float(np.polyfit(t[ok], lag[ok], 1)[0]) if ok.sum() >= 3 and np.ptp(t[ok]) > 0 else float("nan")
    speed = np.radians(np.asarray(dg["speed_deg_s"], float))
    freq = np.radians(np.asarray(dg["accel_deg_s2"], float)) / (2 * math.pi * np.maximum(speed, 1e-6))
    level = max(detect_clip_level(d.gyro_rate) for d in problem.recs)
    top, clipped = [], []
    for d in problem.recs:
        a = np.abs(np.asarray(d.gyro_rate, np.float64))
        top.append(a.max(axis=1))
        t_cam = model.calib.gyro_time_to_camera(d.gyro_t)
        hit = np.zeros(len(d.frame_t), bool)
        if level > 0:
            for ax in range(3):
                for i0, i1, _ in clipped_runs(d.gyro_rate[:, ax], level):
                    a0, a1 = t_cam[i0], t_cam[i1]
                    hit |= (d.frame_t >= a0) & (d.frame_t - 5 * model.calib.tau_s <= a1)
        clipped.append(hit)
    return {"lag_slope_ppm": slope * 1e6, "motion_freq_hz": freq, "gyro_abs_max": np.concatenate(top),
            "clip_level": level, "frame_clipped": np.concatenate(clipped)}
