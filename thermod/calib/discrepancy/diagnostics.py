"""Diagnostic panels: the residual against row, time, angular rate and acceleration, its spatial
spectrum and the kernel-centroid lag. Each effect names the panel that points at it."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from thermod.calib.discrepancy import sensor
from thermod.calib.discrepancy.data import Model, RecData
from thermod.calib.discrepancy.problem import Evaluation, Problem, effective_area
from thermod.physics.calibration import RANGES, Calibration

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
    dg.update(detector_diagnostics(problem, model, ev))
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


# ----------------------------------------------------------------------------------------- detector side
N_MIX_BINS = 12


def detector_diagnostics(problem: Problem, model: Model, ev: Evaluation) -> dict:
    """The panels of the detector-side effects (`sensor`).

    response: mean residual in quantile bins of the variance the blur mixes into each pixel,
    P(r²) − P(r)² (a curved response leaves γ·that: a straight line of slope γ through 0; the residuals
    of τ or an extra PSF are zero-mean at every mixing level). ffc: per-frame residual energy and the
    measured vs predicted frame-to-frame change (in noise units) against time, with the frames that
    did not change although the image moved (frozen: a flat-field correction) and the model's events.
    """
    xs, rs, times, energy, dm_all, dp_all, frozen_all = [], [], [], [], [], [], []
    events = []
    for d, r, p in zip(problem.recs, ev.residuals, ev.predicted, strict=True):
        mv = sensor.mixing_variance(d, model)
        xs.append(mv[d.mask].astype(np.float64))
        rs.append(r[d.mask].astype(np.float64))
        t = d.frame_t - d.t_onset
        times.append(t)
        cnt = np.maximum(d.mask.sum(axis=(1, 2)), 1)
        energy.append(np.sum(r.astype(np.float64) ** 2, axis=(1, 2)) / cnt / max(d.noise_var, 1e-12))
        dm, noise = sensor.temporal_change(d, d.measured, d.mask)
        dp, _ = sensor.temporal_change(d, p, d.mask)
        dm_all.append(dm / noise)
        dp_all.append(dp / noise)
        frozen_all.append(sensor.detect_frozen(d, p, d.mask))
        events += [(e.t_start - d.t_onset, e.t_end - d.t_onset) for e in sensor.events_of(d, model)]
    x, res = np.concatenate(xs), np.concatenate(rs)
    edges = np.unique(np.quantile(x, np.linspace(0, 1, N_MIX_BINS + 1))) if x.size else np.zeros(1)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))
    nb = max(len(edges) - 1, 0)
    bx = np.array([x[idx == i].mean() if np.any(idx == i) else np.nan for i in range(nb)])
    br = np.array([res[idx == i].mean() if np.any(idx == i) else np.nan for i in range(nb)])
    ok = np.isfinite(bx) & np.isfinite(br)
    # through the bins (equal pixel counts), so a few extreme pixels do not set it
    den = float(np.sum(bx[ok] ** 2))
    slope = float(np.sum(bx[ok] * br[ok]) / den) if den > 0 else 0.0
    return {"mix_var": bx, "mix_residual": br, "mix_slope": slope,
            "ffc_t": np.concatenate(times), "frame_energy": np.concatenate(energy),
            "change_measured": np.concatenate(dm_all), "change_predicted": np.concatenate(dp_all),
            "frozen": np.concatenate(frozen_all), "ffc_events": events}


def motion_jacobians(d: RecData, model: Model) -> list[np.ndarray]:
    """The prediction's derivatives (forward differences, canvas and FPN held) with respect to the time
    offset, τ and the readout, float32 [n, h, w] each. Per frame they span the first-order traces of an
    error of the motion along its own direction: when it happens (offset, and per row: readout) and how
    far it reaches (a rate error δω/ω stretches the comet tail, of length |ω|τ, like a τ error δτ/τ)."""
    c = model.calib
    period = 1.0 / c.frame_rate_hz
    ro = c.readout_s + 1e-3 if c.readout_s + 1e-3 <= period else c.readout_s - 1e-3
    # each step stays inside the field's range (a model at its upper end steps down)
    off = c.time_offset_s + (1e-3 if c.time_offset_s + 1e-3 <= RANGES["time_offset_s"][1] else -1e-3)
    tau = c.tau_s * (1.05 if 1.05 * c.tau_s <= RANGES["tau_s"][1] else 0.95)
    steps = [c.replace(time_offset_s=off), c.replace(tau_s=tau), c.replace(readout_s=ro)]
    base, _ = sensor.predict(d, model)
    # only the span matters: each derivative is left in counts per step
    return [sensor.predict(d, dataclasses.replace(model, calib=cs))[0] - base for cs in steps]


def response_signature(problem: Problem, model: Model, ev: Evaluation) -> tuple[float, float]:
    """Slope (per count) and z score of the residual against the variance the blur mixes into each
    pixel, P(r²) − P(r)², through 0: the trace of a curved response x = u + γu² applied after the blur,
    −γ·that with one γ in every frame and pixel whatever the frame's motion (Jensen's gap).

    A wrong motion (a clipped gyro, timing, τ) leaves residual where and when the motion is wrong,
    which can follow the mixing variance there (both grow with the blur). So, frame by frame, the
    first-order traces of an error along that frame's motion (`motion_jacobians`) are taken out of
    residual and regressor alike, and each frame counts with its own residual variance about the fit
    (generalised least squares, iterated once): a frame the motion model gets wrong carries that error
    as noise instead of setting the slope. The standard error counts one independent sample per
    `effective_area` pixels of the standardised residual, so correlated residuals do not inflate z."""
    frames = []     # (recording index, frame, regressor, residual, noise variance) after the partialling
    for i, (d, r) in enumerate(zip(problem.recs, ev.residuals, strict=True)):
        mv = sensor.mixing_variance(d, model)
        jac = motion_jacobians(d, model)
        for k in range(len(r)):
            m = d.mask[k]
            if m.sum() <= 2 * len(jac):
                continue
            Q = np.stack([j[k][m] for j in jac], axis=1).astype(np.float64)
            Q /= np.maximum(np.linalg.norm(Q, axis=0), 1e-12)
            xy = np.stack([mv[k][m], r[k][m]], axis=1).astype(np.float64)
            xy -= Q @ np.linalg.lstsq(Q, xy, rcond=1e-6)[0]
            frames.append((i, k, xy[:, 0], xy[:, 1], max(d.noise_var, 1e-12)))
    slope, den, var = 0.0, 0.0, []
    for _ in range(2):
        var = [max(float(np.mean((y - slope * x) ** 2)), nv) for _, _, x, y, nv in frames]
        den = sum(float(x @ x) / v for (_, _, x, _, _), v in zip(frames, var, strict=True))
        if den <= 0:
            return 0.0, 0.0
        slope = sum(float(x @ y) / v for (_, _, x, y, _), v in zip(frames, var, strict=True)) / den
    std = [np.zeros(r.shape, np.float32) for r in ev.residuals]
    for (i, k, x, y, _), v in zip(frames, var, strict=True):
        std[i][k][problem.recs[i].mask[k]] = (y - slope * x) / math.sqrt(v)
    return slope, slope * math.sqrt(den / effective_area(std))


def pooled_response_signature(problem: Problem, model: Model, ev: Evaluation) -> tuple[float, float]:
    """The same regression with nothing taken out and one variance for every pixel: (slope per count,
    z). It sees a forward model's trace and a wrong motion's as well as a curved response's; a curved
    response is the one trace that both it and `response_signature` see, with one sign."""
    num = den = rss = 0.0
    n = 0
    for d, r in zip(problem.recs, ev.residuals, strict=True):
        x = sensor.mixing_variance(d, model)[d.mask].astype(np.float64)
        y = r[d.mask].astype(np.float64)
        num += float(x @ y)
        den += float(x @ x)
        rss += float(y @ y)
        n += len(y)
    if den <= 0 or n < 2:
        return 0.0, 0.0
    slope = num / den
    var = max(rss - slope * num, 0.0) / n
    se = math.sqrt(var * effective_area(ev.residuals) / den)
    return slope, (slope / se if se > 0 else 0.0)
