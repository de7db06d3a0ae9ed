"""Model-discrepancy workflow: which effect is missing from the calibration, and how large is it?

`thermod discrepancy REC.h5 [REC2.h5 …] --out DIR [--config model.toml]`

A recording made by the payload starts with a static segment (the gyro reads ≈ its bias) followed
by motion. The workflow

1. builds a **reference scene** from the static frames (their mean: the detector is settled and the
   camera still, so this is the sharp view, with the static optical PSF and the fixed-pattern noise);
2. **predicts** every motion frame from the reference, the raw gyro and the current model with
   `thermod.calib.forward.ForwardModel` (Eq. 16 homographies, Eq. 10/11 thermal IIR at sub-pixel steps,
   rolling readout, extra Gaussian PSF) at a reduced working resolution;
3. measures the **gap**: ``gap = ‖measured − predicted‖ / ‖measured − reference‖`` over the pixels
   valid in every view (1 = the model explains nothing of the motion signal, 0 = everything), with
   the **noise floor** the gap a perfect model would leave, from the static frames' temporal noise;
4. fits each **candidate effect** (time_offset, rolling_readout, gyro_bias, gyro_scale,
   misalignment, time_constant, optical_psf): coarse search, then bounded refinement. A candidate is
   accepted only if its BIC gain on *effective* independent residual samples (pixel correlation
   measured from the residual's autocorrelation) is decisive and it removes a sizeable fraction of
   the gap's excess over the noise floor; the best one is added to the model, the effects named
   before it are refitted with it in place (they may have absorbed part of it), and the loop repeats;
   the gyro bias also uses the static segment's mean raw rate as a prior (a direct measurement);
5. says ``unexplained: true`` when the remaining residual is still well above the noise floor but no
   candidate explains it, rather than naming a wrong effect.

Fixed-pattern noise (FPN) sits still on the sensor while the scene moves, so it is estimated as the
temporal mean of the motion residual and added back to every prediction (and removed from the
reference before warping). The optical PSF of the static frames is in the reference already: the
`optical_psf` candidate fits the *extra* blur σ_e of motion frames and reports the model's Eq. 19 σ
as √(σ_nominal² + σ_e²) (the static blur is taken to be the nominal one). A PSF that static and
moving frames share is therefore *unobservable* from this comparison — the workflow leaves it alone.
Parameters the motion does not excite (a gyro axis that barely turns; misalignment directions about
the only rotation axis) are not fitted and are listed under `unobservable`.

The forward model's own precision (resampling at the working resolution, ≈ 1–5 % of the motion
signal on simulator data) is allowed for by `model_tol` in both the search and the verdict.

Outputs: DIR/report.json, DIR/report.md, DIR/model.toml and PNG figures (residual maps before and
after every step, gap per step, the diagnostic panel that pointed at each effect).
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import optimize

from thermod.calib.forward import ForwardModel, downsample
from thermod.errors import ConfigError, RecordingError
from thermod.io import recording as recording_io
from thermod.physics.calibration import Calibration
from thermod.physics.geometry import so3_log

log = logging.getLogger("thermod.calib.discrepancy")

__all__ = ["CANDIDATES", "Analysis", "Model", "analyse", "prepare", "write_report"]

CANDIDATES = ("time_offset", "rolling_readout", "gyro_bias", "gyro_scale", "misalignment",
              "time_constant", "optical_psf")


# ----------------------------------------------------------------------------------------- model
@dataclass(frozen=True)
class Model:
    """The calibration under test plus the extra optical blur of motion frames (px, full resolution)."""

    calib: Calibration
    extra_psf_px: float = 0.0

    def final_calibration(self) -> Calibration:
        """Calibration with the extra blur folded into Eq. 19's σ (static blur taken as nominal)."""
        if self.extra_psf_px <= 0:
            return self.calib
        sigma = math.hypot(self.calib.psf_sigma_px, self.extra_psf_px)
        return self.calib.with_psf_sigma_px(sigma)


# ----------------------------------------------------------------------------------------- data
@dataclass
class RecData:
    """One recording prepared for the fit (everything at the working resolution)."""

    name: str
    fm: ForwardModel
    measured: np.ndarray          # float32 [n, h, w] motion frames
    frame_t: np.ndarray           # their camera times (nominal model)
    static_mean: np.ndarray       # float32 [h, w] reference incl. FPN
    reference_full: np.ndarray    # float32 [H, W] static mean at full resolution
    noise_var: float              # temporal variance of one static frame (working res)
    n_static: int
    t_ref: float
    t_onset: float
    gyro_t: np.ndarray
    gyro_rate: np.ndarray
    static_gyro_mean: np.ndarray | None
    static_gyro_sem: np.ndarray | None    # standard error of that mean (rad/s)
    motion_rms_rad_s: np.ndarray  # per gyro axis, bias-removed
    fpn: np.ndarray | None = None
    mask: np.ndarray | None = None


def detect_static(gyro_t, gyro_rate, *, head_s: float = 0.05, min_rate: float = math.radians(0.5),
                  k_sigma: float = 8.0, smooth_s: float = 0.005):
    """Gyro-clock time at which the motion starts, and the static samples' mean raw rate.

    The rate during the first `head_s` sets the baseline (bias) and noise; the motion starts where the
    smoothed deviation from the baseline first exceeds max(k_sigma·noise, min_rate).
    Returns (t_onset or None if there is no motion, static mean rate or None if too short).
    """
    t = np.asarray(gyro_t, np.float64)
    r = np.asarray(gyro_rate, np.float64)
    if len(t) < 10:
        return None, None
    dt = float(np.median(np.diff(t)))
    n_head = max(5, int(head_s / dt))
    base = np.median(r[:n_head], axis=0)
    dev = np.linalg.norm(r - base, axis=1)
    # white-noise σ from sample-to-sample differences (robust even if the head is already moving)
    noise = 1.4826 * float(np.median(np.abs(np.diff(r[:n_head], axis=0)))) / math.sqrt(2.0) * math.sqrt(3.0)
    thr = max(k_sigma * noise, min_rate)
    win = max(1, int(round(smooth_s / dt)))
    sm = np.convolve(dev, np.ones(win) / win, mode="same")
    above = np.flatnonzero(sm > thr)
    if len(above) == 0:
        return None, r.mean(axis=0)
    i0 = int(above[0])
    t_onset = float(t[i0] - smooth_s)
    static = t < t_onset - smooth_s
    mean = r[static].mean(axis=0) if static.sum() >= 5 else None
    return t_onset, mean


def _static_sem(gyro_t, gyro_rate, t_onset_gyro):
    r = np.asarray(gyro_rate, np.float64)[np.asarray(gyro_t) < t_onset_gyro - 0.005]
    if len(r) < 5:
        return None
    # white-noise σ from differences (immune to slow drift), /√n for the mean
    return np.std(np.diff(r, axis=0), axis=0) / math.sqrt(2.0) / math.sqrt(len(r))


def prepare(rec: recording_io.Recording, calib: Calibration, *, name: str = "<recording>",
            scale: float | None = None, work_width: int = 160, offset_margin_s: float = 0.03,
            max_step_px: float = 0.5, smooth_px: float = 0.0) -> RecData:
    """Split a recording into reference and motion frames and build its forward model.

    Raises RecordingError (naming `name`) when there is no static segment, no motion or no gyro
    coverage of the motion frames.
    """
    if (rec.frames.shape[1], rec.frames.shape[2]) != (calib.height, calib.width):
        raise RecordingError(name, "camera/frames", f"frame size {rec.frames.shape[2]}×{rec.frames.shape[1]}"
                             f" does not match the model's width×height {calib.width}×{calib.height}")
    if scale is None:
        scale = 1.0
        while calib.width * scale > 1.5 * work_width and scale > 1 / 16:
            scale /= 2.0
    t_on_g, static_mean_rate = detect_static(rec.gyro_t, rec.gyro_rate)
    if t_on_g is None:
        raise RecordingError(name, "gyro/rate", "no motion found: the workflow needs a static segment "
                             "followed by motion")
    t_onset = t_on_g + calib.time_offset_s
    t_ref = t_onset - offset_margin_s
    static = rec.t <= t_ref
    n_static = int(static.sum())
    if n_static < 3:
        raise RecordingError(name, "camera/frames", f"only {n_static} frames before the motion starts at "
                             f"t={t_onset:.3f} s (minus a {offset_margin_s * 1e3:.0f} ms margin for the time "
                             "offset); need ≥ 3 static frames for a reference")
    gyro_end = rec.gyro_t[-1] + calib.time_offset_s - offset_margin_s
    moving = (rec.t > t_ref) & (rec.t <= gyro_end)
    if moving.sum() < 2:
        raise RecordingError(name, "camera/t", "fewer than 2 frames during the motion are covered by gyro "
                             "samples")
    st = rec.frames[static].astype(np.float32)
    ref_full = st.mean(axis=0)
    st_w = downsample(st, scale, smooth_px)
    static_mean = st_w.mean(axis=0)
    noise_var = float(np.mean((st_w - static_mean) ** 2) * n_static / max(n_static - 1, 1))
    frame_t = rec.t[moving]
    fm = ForwardModel(ref_full, frame_t, rec.gyro_t, rec.gyro_rate, calib, t_ref=t_ref, scale=scale,
                      max_step_px=max_step_px)
    fm.set_reference(static_mean, None, prescaled=True)
    measured = downsample(rec.frames[moving], scale, smooth_px)
    gm = rec.gyro_t + calib.time_offset_s > t_onset
    base = static_mean_rate if static_mean_rate is not None else np.zeros(3)
    motion_rms = np.sqrt(np.mean((rec.gyro_rate[gm] - base) ** 2, axis=0)) if gm.any() else np.zeros(3)
    return RecData(name, fm, measured, frame_t, static_mean, ref_full, noise_var, n_static, t_ref, t_onset,
                   rec.gyro_t, rec.gyro_rate, static_mean_rate,
                   _static_sem(rec.gyro_t, rec.gyro_rate, t_on_g),
                   motion_rms)


# ----------------------------------------------------------------------------------------- cost
@dataclass
class Evaluation:
    ssr: float
    n: int
    residuals: list          # per recording float32 [n, h, w] (masked pixels 0)
    predicted: list


class Problem:
    """Residuals of all recordings under a candidate model, over fixed per-step masks."""

    def __init__(self, recs: list[RecData]):
        self.recs = recs
        self.n_evals = 0
        # Set per step by `analyse`: SSR of one independent χ² unit (noise variance × pixels per
        # independent sample), the effective sample count, and the least SSR gain worth a parameter.
        self.chi2_scale = 1.0
        self.n_eff = 1000.0
        self.min_gain = 0.0
        self.named: list[str] = []

    def predict(self, model: Model, d: RecData):
        self.n_evals += 1
        return d.fm.predict(model.calib, model.extra_psf_px)

    def evaluate(self, model: Model, keep=False) -> Evaluation:
        ssr, n, res, preds = 0.0, 0, [], []
        for d in self.recs:
            p, _ = self.predict(model, d)
            r = (d.measured - p) * d.mask
            ssr += float(np.sum(r.astype(np.float64) ** 2))
            n += int(d.mask.sum())
            if keep:
                res.append(r)
                preds.append(p)
        return Evaluation(ssr, n, res, preds)

    def residual_vector(self, model: Model) -> np.ndarray:
        out = []
        for d in self.recs:
            p, _ = self.predict(model, d)
            out.append((d.measured - p)[d.mask].astype(np.float64))
        return np.concatenate(out)

    def refresh(self, model: Model, fpn: bool = True, erode_px: int = 2, fpn_iters: int = 2,
                fpn_highpass_px: float = 1.5):
        """Per-step state: FPN estimate and the fixed valid mask.

        FPN stays put on the sensor while the scene moves, so it is what the motion residual has in
        common over time: F ← F + HP(mean_k r_k), iterated from F = 0 under the current model. Only
        its high-pass part is kept: low spatial frequencies are nearly the same in the reference and
        the moved views (so they barely matter) and would absorb slow model errors instead.
        """
        import cv2

        for d in self.recs:
            d.fpn = None
            if fpn:
                F = np.zeros_like(d.static_mean)
                for _ in range(fpn_iters):
                    d.fm.set_reference(d.static_mean, F, prescaled=True)
                    p, v = d.fm.predict(model.calib, model.extra_psf_px)
                    r = np.where(v, d.measured - p, 0.0)
                    cnt = v.sum(axis=0)
                    upd = np.where(cnt > 0, r.sum(axis=0) / np.maximum(cnt, 1), 0.0).astype(np.float32)
                    upd -= cv2.GaussianBlur(upd, (0, 0), fpn_highpass_px, borderType=cv2.BORDER_REPLICATE)
                    F = F + upd
                d.fpn = F
            d.fm.set_reference(d.static_mean, d.fpn, prescaled=True)
            _, v = d.fm.predict(model.calib, model.extra_psf_px)
            k = np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8)
            m = np.stack([cv2.erode(x.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
                          for x in v]).astype(bool)
            d.mask = m

    def signal_ss(self) -> float:
        return float(sum(np.sum(((d.measured - d.static_mean) * d.mask).astype(np.float64) ** 2)
                         for d in self.recs))

    def noise_ss(self) -> float:
        """Expected SSR of a perfect model: frame noise + reference noise, minus the FPN fit's share."""
        tot = 0.0
        for d in self.recs:
            n_m = max(len(d.frame_t), 2)
            f = (1.0 + 1.0 / d.n_static) * ((1.0 - 1.0 / n_m) if d.fpn is not None else 1.0)
            tot += d.noise_var * f * float(d.mask.sum())
        return tot


def effective_area(residuals: list, max_lag: int = 6) -> float:
    """Σρ(d)² of the residual's spatial autocorrelation: pixels per independent sample (≥ 1).

    The variance of a sum of squares of correlated Gaussian samples is inflated by Σρ², so
    N_eff = N / Σρ² is the honest sample count for the BIC.
    """
    acc, w = None, 0
    for r in residuals:
        for fr in r[:: max(1, len(r) // 6)]:
            x = fr - fr[fr != 0].mean() if np.any(fr != 0) else fr
            x = np.where(fr != 0, x, 0.0)
            F = np.fft.rfft2(x, s=(2 * x.shape[0], 2 * x.shape[1]))
            ac = np.fft.irfft2(np.abs(F) ** 2, s=(2 * x.shape[0], 2 * x.shape[1]))
            acc = ac if acc is None else acc + ac
            w += 1
    if acc is None or acc[0, 0] <= 0:
        return 1.0
    rho = acc / acc[0, 0]
    lags = np.r_[0:max_lag + 1, -max_lag:0]
    sub = rho[np.ix_(lags, lags)]
    return float(max(1.0, np.sum(sub**2)))


# ----------------------------------------------------------------------------------------- effects
@dataclass
class FitResult:
    effect: str
    model: Model
    params: dict
    ssr: float
    unobservable: list = field(default_factory=list)
    n_params: int = 1
    note: str = ""


def _scalar_fit(problem: Problem, model: Model, make, grid, lo, hi, refine_width):
    """Coarse grid then bounded Brent refinement of a one-parameter family `make(x) -> Model`."""
    costs = [problem.evaluate(make(x)).ssr for x in grid]
    i = int(np.argmin(costs))
    a = max(lo, grid[max(i - 1, 0)] if refine_width is None else grid[i] - refine_width)
    b = min(hi, grid[min(i + 1, len(grid) - 1)] if refine_width is None else grid[i] + refine_width)
    if b <= a:
        return grid[i], costs[i]
    res = optimize.minimize_scalar(lambda x: problem.evaluate(make(x)).ssr, bounds=(a, b), method="bounded",
                                   options={"xatol": (b - a) * 2e-3, "maxiter": 15})
    if res.fun < costs[i]:
        return float(res.x), float(res.fun)
    return float(grid[i]), float(costs[i])


def _vector_fit(problem: Problem, model: Model, make, x0s, unit, bound, iters: int = 6, h: float = 0.25,
                prior=None):
    """Levenberg–Marquardt on the residual vector from the best of several starts (x in `unit`s).

    The Jacobian is a forward difference with a step of `h` units: the forward model is only
    smooth down to its resampling precision, so steps must move the image by a good fraction of
    a pixel, not by float rounding. `prior` = (x_p, w): an independent measurement x_p of x with
    weight w (SSR units per unit²) appended as extra residuals √w (x − x_p). Returns the fitted
    parameters and the image SSR alone (what the selection compares).
    """
    def pres(x):
        return np.zeros(0) if prior is None else np.sqrt(prior[1]) * (x - prior[0])

    def cost(x):
        p = pres(x)
        return problem.evaluate(make(x * unit)).ssr + float(p @ p)

    best = None
    for x0 in x0s:
        x0 = np.clip(np.asarray(x0, float), -bound, bound)
        c = cost(x0)
        if best is None or c < best[1]:
            best = (x0, c)
    x, c = best
    if len(x) == 0:
        return x * unit, problem.evaluate(make(x * unit)).ssr
    lam = 1e-3
    for _ in range(iters):
        r0 = np.concatenate([problem.residual_vector(make(x * unit)), pres(x)])
        c = float(r0 @ r0)
        J = np.empty((len(r0), len(x)))
        for i in range(len(x)):
            e = np.zeros(len(x))
            e[i] = h if x[i] + h <= bound else -h
            r1 = np.concatenate([problem.residual_vector(make((x + e) * unit)), pres(x + e)])
            J[:, i] = (r1 - r0) / e[i]
        g = J.T @ r0
        A = J.T @ J
        improved = False
        for _ in range(4):
            step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
            xn = np.clip(x + step, -bound, bound)
            cn = cost(xn)
            if cn < c:
                x, lam, improved = xn, lam / 3, True
                break
            lam *= 10
        if not improved or np.max(np.abs(step)) < 0.02:
            break
    return x * unit, problem.evaluate(make(x * unit)).ssr


def fit_time_offset(problem, model, recs, max_offset_s=0.03):
    c0 = model.calib
    t0 = c0.time_offset_s
    grid = t0 + np.arange(-max_offset_s, max_offset_s + 1e-9, 0.005)

    def make(x):
        return Model(c0.replace(time_offset_s=float(x)), model.extra_psf_px)
    x, ssr = _scalar_fit(problem, model, make, grid, t0 - max_offset_s, t0 + max_offset_s, 0.005)
    return FitResult("time_offset", make(x), {"time_offset_s": x}, ssr)


def fit_rolling_readout(problem, model, recs):
    """Readout time T_ro ∈ [0, frame period]. Rows are read T_ro/2 early on average, so a time offset
    fitted before the readout has absorbed that shift: once `time_offset` is in the model the readout is
    also tried with the offset moved by −ΔT_ro/2 (mid-frame timing kept), and the better one is kept."""
    c0 = model.calib
    hi = 1.0 / c0.frame_rate_hz
    grid = np.linspace(0.0, hi, 11)

    def make(x):
        return Model(c0.replace(readout_s=float(x)), model.extra_psf_px)

    def make_centred(x):
        off = c0.time_offset_s - 0.5 * (float(x) - c0.readout_s)
        return Model(c0.replace(readout_s=float(x), time_offset_s=off), model.extra_psf_px)

    x, ssr = _scalar_fit(problem, model, make, grid, 0.0, hi, None)
    best = FitResult("rolling_readout", make(x), {"readout_s": x}, ssr)
    if "time_offset" in problem.named:
        xc, ssrc = _scalar_fit(problem, model, make_centred, grid, 0.0, hi, None)
        if ssrc < ssr:
            m = make_centred(xc)
            best = FitResult("rolling_readout", m, {"readout_s": xc, "time_offset_s": m.calib.time_offset_s},
                             ssrc)
    return best


def fit_time_constant(problem, model, recs):
    c0 = model.calib
    lo, hi = math.log(c0.tau_s / 3.0), math.log(c0.tau_s * 3.0)
    grid = np.linspace(lo, hi, 13)

    def make(x):
        return Model(c0.replace(tau_s=float(math.exp(x))), model.extra_psf_px)
    x, ssr = _scalar_fit(problem, model, make, grid, lo, hi, None)
    return FitResult("time_constant", make(x), {"tau_s": math.exp(x)}, ssr)


def fit_optical_psf(problem, model, recs):
    c0 = model.calib
    grid = np.linspace(0.0, 3.0, 13)

    def make(x):
        return Model(c0, float(math.hypot(model.extra_psf_px, x)))
    x, ssr = _scalar_fit(problem, model, make, grid, 0.0, 3.0, None)
    m = make(x)
    return FitResult("optical_psf", m, {"psf_sigma_px": m.final_calibration().psf_sigma_px,
                                        "extra_sigma_px": m.extra_psf_px}, ssr)


def _axis_observable(recs, min_rms=0.0175, rel=0.1):
    """Gyro axes whose motion RMS (rad/s) is ≥ min_rms (1 °/s) and ≥ rel × the strongest axis."""
    rms = np.sqrt(np.mean([d.motion_rms_rad_s**2 for d in recs], axis=0))
    return (rms >= min_rms) & (rms >= rel * rms.max())


def fit_gyro_bias(problem, model, recs, bias_stability_rad_s: float = math.radians(0.05)):
    """Bias: the static segment measures it directly (the camera is still, the gyro reads its bias),
    so its mean enters as a prior with its standard error ⊕ `bias_stability_rad_s` (drift between
    the static and the moving part); the images refine it. The prior's weight puts both on the
    same χ² scale: image SSR / (residual variance × pixels per independent sample)."""
    c0 = model.calib
    b0 = np.asarray(c0.bias_rad_s, float)
    unit = math.radians(0.2)
    starts = [np.zeros(3)]
    prior = None
    sm = [d.static_gyro_mean for d in recs if d.static_gyro_mean is not None]
    if sm:
        xs = (np.mean(sm, axis=0) - b0) / unit
        starts.append(xs)
        sem = [d.static_gyro_sem for d in recs if d.static_gyro_sem is not None]
        sem = np.sqrt(np.mean(np.square(sem), axis=0) / len(sem)) if sem else np.zeros(3)
        sigma = np.sqrt(sem**2 + bias_stability_rad_s**2) / unit          # in units
        w = problem.chi2_scale / sigma**2
        prior = (xs, w)

    def make(x):
        return Model(c0.replace(bias_rad_s=tuple(float(v) for v in b0 + x)), model.extra_psf_px)
    x, ssr = _vector_fit(problem, model, make, starts, unit, bound=100.0, prior=prior)   # ±20 °/s
    m = make(x)
    return FitResult("gyro_bias", m, {"bias_rad_s": list(m.calib.bias_rad_s)}, ssr, n_params=3)


def fit_gyro_scale(problem, model, recs, bic_min: float = 10.0):
    """Scale factor: one common factor first, per-axis factors only if the BIC on effective samples
    prefers the two extra parameters (Occam: a common error is the usual case and the per-axis fit of
    a weakly excited axis, typically roll, is noisy). Axes the motion barely excites are not fitted."""
    c0 = model.calib
    s0 = c0.scale_vector
    obs = _axis_observable(recs)
    idx = np.flatnonzero(obs)
    unit = 0.01
    un = [f"scale[{a}]" for a in range(3) if not obs[a]]

    def make_common(x):
        s = s0.copy()
        s[idx] = s0[idx] * (1.0 + float(np.asarray(x).ravel()[0]))
        return Model(c0.replace(scale=tuple(float(v) for v in s)), model.extra_psf_px)

    def make_axes(x):
        s = s0.copy()
        s[idx] = s0[idx] * (1.0 + np.asarray(x))
        return Model(c0.replace(scale=tuple(float(v) for v in s)), model.extra_psf_px)

    if len(idx) == 0:
        return FitResult("gyro_scale", model, {"scale": list(c0.scale)}, problem.evaluate(model).ssr,
                         unobservable=un, n_params=0)
    x1, ssr1 = _vector_fit(problem, model, make_common, [np.zeros(1)], unit, bound=20.0)
    best, n_par = (make_common(x1), ssr1), 1
    if len(idx) > 1:
        x3, ssr3 = _vector_fit(problem, model, make_axes, [np.full(len(idx), x1[0] / unit)], unit, bound=20.0)
        n_eff = problem.n_eff
        dbic = n_eff * math.log(ssr1 / max(ssr3, 1e-30)) - (len(idx) - 1) * math.log(n_eff)
        if dbic > bic_min and ssr1 - ssr3 >= problem.min_gain:
            best, n_par = (make_axes(x3), ssr3), len(idx)
    m, ssr = best
    return FitResult("gyro_scale", m, {"scale": list(m.calib.scale)}, ssr, unobservable=un, n_params=n_par)


def fit_misalignment(problem, model, recs):
    """Extra camera-side rotation δ: ω_cam' = exp(δ) ω_cam. Only directions the motion excites are fitted:
    Δω ≈ δ × ω, whose information matrix Σ(|ω|² I − ω ωᵀ) is singular for single-axis motion."""
    c0 = model.calib
    Ms = []
    for d in recs:
        _, w = c0.gyro_to_camera(d.gyro_t, d.gyro_rate)
        w = w[d.gyro_t + c0.time_offset_s > d.t_onset]
        if len(w):
            Ms.append(np.sum(w**2) * np.eye(3) - w.T @ w)
    M = np.sum(Ms, axis=0) if Ms else np.zeros((3, 3))
    ev, evec = np.linalg.eigh(M)
    keep = ev > 0.05 * max(ev.max(), 1e-12)
    basis = evec[:, keep]
    unit = math.radians(0.5)

    def make(x):
        return Model(c0.with_misalignment(basis @ np.asarray(x)), model.extra_psf_px)
    x, ssr = _vector_fit(problem, model, make, [np.zeros(basis.shape[1])], unit, bound=20.0)   # ±10°
    m = make(x)
    rotvec = basis @ (np.asarray(x) if len(x) else np.zeros(0))
    un = [f"rotation about {np.round(evec[:, i], 2).tolist()}" for i in np.flatnonzero(~keep)]
    return FitResult("misalignment", m, {"rotvec_rad": [float(v) for v in rotvec]}, ssr, unobservable=un,
                     n_params=int(keep.sum()))


FITTERS = {
    "time_offset": fit_time_offset,
    "rolling_readout": fit_rolling_readout,
    "gyro_bias": fit_gyro_bias,
    "gyro_scale": fit_gyro_scale,
    "misalignment": fit_misalignment,
    "time_constant": fit_time_constant,
    "optical_psf": fit_optical_psf,
}

# Which diagnostic panel points at which effect (see `diagnostics`).
DIAGNOSTIC_FOR = {
    "time_offset": "lag", "rolling_readout": "row", "gyro_bias": "time", "gyro_scale": "rate",
    "misalignment": "rate", "time_constant": "accel", "optical_psf": "spectrum",
}


# ----------------------------------------------------------------------------------------- diagnostics
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
    import cv2

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


def diagnostics(problem: Problem, model: Model, ev: Evaluation) -> dict:
    """Residual vs row, time, angular rate and acceleration, spectrum and centroid lag (all recordings)."""
    rows, rows_sig, times, frame_rel, speeds, accs, lags = None, None, [], [], [], [], []
    spec, spec_noise = None, 0.0
    for d, r, p in zip(problem.recs, ev.residuals, ev.predicted, strict=True):
        m = d.mask
        # relative to the motion signal, so scene content does not masquerade as structure
        sig = ((d.measured - d.static_mean) * m).astype(np.float64) ** 2
        ss = np.sum(r.astype(np.float64) ** 2, axis=(0, 2))
        rows = ss if rows is None else rows + ss
        rows_sig = sig.sum(axis=(0, 2)) if rows_sig is None else rows_sig + sig.sum(axis=(0, 2))
        fr = np.sqrt(np.sum(r.astype(np.float64) ** 2, axis=(1, 2)) / np.maximum(sig.sum(axis=(1, 2)), 1e-12))
        frame_rel.append(fr)
        times.append(d.frame_t - d.t_onset)
        rate, acc = _frame_rates(d, model.calib)
        speeds.append(np.degrees(np.linalg.norm(rate, axis=1)))
        accs.append(np.degrees(np.linalg.norm(acc, axis=1)))
        lags.append(_centroid_lag(d, model.calib, r, p))
        P = np.mean(np.abs(np.fft.fft2(r)) ** 2, axis=0) / r[0].size
        h, w = P.shape
        fy, fx = np.meshgrid(np.fft.fftfreq(h), np.fft.fftfreq(w), indexing="ij")
        rad = np.hypot(fy, fx)
        bins = np.linspace(0, 0.5, 11)
        idx = np.digitize(rad.ravel(), bins) - 1
        s = np.array([P.ravel()[idx == i].mean() if np.any(idx == i) else 0.0 for i in range(10)])
        spec = s if spec is None else spec + s
        spec_noise += d.noise_var * float(m.mean())
    nrec = len(problem.recs)
    noise_sd = math.sqrt(sum(d.noise_var for d in problem.recs) / nrec)
    lag = np.concatenate(lags)
    return {
        "row_gap": np.sqrt(rows / np.maximum(rows_sig, 1e-12)), "noise_sd": noise_sd,
        "t": np.concatenate(times), "frame_gap": np.concatenate(frame_rel),
        "speed_deg_s": np.concatenate(speeds), "accel_deg_s2": np.concatenate(accs),
        "lag_s": lag, "lag_median_s": float(np.nanmedian(lag)) if np.any(np.isfinite(lag)) else float("nan"),
        "spectrum": spec / nrec, "spectrum_noise": spec_noise / nrec,
        "spectrum_freq": (np.arange(10) + 0.5) * 0.05,
    }


# ----------------------------------------------------------------------------------------- analysis
@dataclass
class Analysis:
    gap_initial: float
    gap_final: float
    noise_floor: float
    steps: list
    unexplained: bool
    model: Model
    nominal: Model
    snapshots: list = field(default_factory=list)   # (label, residual map, gap) for figures
    diags: list = field(default_factory=list)        # (effect named, diagnostics before it)
    gaps: list = field(default_factory=list)
    candidates_tried: list = field(default_factory=list)
    unobservable: dict = field(default_factory=dict)
    seconds: float = 0.0

    def report(self) -> dict:
        return {
            "gap_initial": self.gap_initial, "gap_final": self.gap_final, "noise_floor": self.noise_floor,
            "steps": self.steps, "unexplained": self.unexplained,
            "model": self.model.final_calibration().as_dict(),
            "nominal": self.nominal.final_calibration().as_dict(),
            "unobservable": self.unobservable, "candidates": self.candidates_tried,
            "definition": "gap = ||measured - predicted|| / ||measured - static reference|| over pixels "
                          "valid "
                          "in every view of the working-resolution motion frames; noise_floor = the gap of a "
                          "perfect model given the static segment's temporal noise",
            "seconds": self.seconds,
        }


def _gap(problem: Problem, ssr: float) -> float:
    return math.sqrt(ssr / max(problem.signal_ss(), 1e-30))


def _mean_residual_map(ev: Evaluation, problem: Problem) -> np.ndarray:
    d, r = problem.recs[0], ev.residuals[0]
    return np.sqrt(np.sum(r.astype(np.float64) ** 2, axis=0) / np.maximum(d.mask.sum(axis=0), 1))


def analyse(recs: list[RecData], model: Model, *, candidates=CANDIDATES, max_steps: int = 4,
            bic_min: float = 10.0, min_explained: float = 0.3, structured_excess: float = 0.3,
            unexplained_excess: float = 1.0, model_tol: float = 0.05, fpn: bool = True,
            polish: bool = True, min_pixels: int = 2000, progress=None) -> Analysis:
    """Greedy search for the missing effects (see the module docstring for the criteria).

    `structured_excess`: candidates are tried while SSR exceeds the noise expectation by this
    fraction (gap > √(1+x)·noise floor). `unexplained_excess`: what is left at the end counts as
    structured-but-unexplained above this larger fraction, which leaves room for the forward
    model's own approximation error. `model_tol`: the forward model's relative precision (gap units:
    resampling and interpolation at the working resolution, measured at 0.01–0.05 of the motion
    signal on simulator recordings; largest for sharp-edged scenes). Candidates are tried when
    ``SSR > noise·(1 + structured_excess) + (½ model_tol·‖signal‖)²`` and the rest is called
    unexplained when ``SSR > noise·(1 + unexplained_excess) + (model_tol·‖signal‖)²``; a candidate
    must also remove at least (model_tol·‖signal‖)² of SSR.
    `min_explained`: a candidate must remove at least this
    fraction of the excess SSR. `bic_min`: decisive BIC gain on effective samples.
    """
    say = progress or (lambda msg: None)
    t_start = time.monotonic()
    unknown = [c for c in candidates if c not in FITTERS]
    if unknown:
        raise ConfigError(f"discrepancy: unknown candidate effect(s) {unknown}; known: {list(FITTERS)}")
    problem = Problem(recs)
    nominal = model
    problem.refresh(model, fpn=fpn)
    for d in recs:
        if d.mask.sum() < min_pixels:
            raise RecordingError(d.name, "camera/frames", f"only {int(d.mask.sum())} pixels of the motion "
                                 f"frames stay inside the static reference view (need ≥ {min_pixels}); "
                                 "record a smaller motion or start it from the middle of the scene")
    ev = problem.evaluate(model, keep=True)
    gap0 = _gap(problem, ev.ssr)
    floor = math.sqrt(problem.noise_ss() / max(problem.signal_ss(), 1e-30))
    say(f"gap {gap0:.4f} (noise floor {floor:.4f}) over {ev.n} pixels of {sum(len(d.frame_t) for d in recs)} "
        f"motion frames at {recs[0].fm.w}×{recs[0].fm.h}")
    ana = Analysis(gap0, gap0, floor, [], False, model, nominal)
    ana.snapshots.append(("nominal", _mean_residual_map(ev, problem), gap0))
    ana.gaps.append(("nominal", gap0, floor))
    remaining = list(candidates)
    def allowance(x, tol):
        return problem.noise_ss() * (1.0 + x) + tol**2 * problem.signal_ss()

    for _ in range(max_steps):
        noise_ss = problem.noise_ss()
        if ev.ssr <= allowance(structured_excess, 0.5 * model_tol) or not remaining:
            break
        area = effective_area(ev.residuals)
        n_eff = ev.n / area
        # χ² unit at the noise level (not the current residual's): a wrong model must not drown priors
        problem.chi2_scale = noise_ss / max(ev.n, 1) * area
        problem.n_eff = n_eff
        problem.named = [st["effect"] for st in ana.steps]
        # Practical significance too: what a candidate explains must exceed the forward model's own
        # imprecision (model_tol of the motion signal), or it is fitting resampling error.
        problem.min_gain = min_gain = model_tol ** 2 * problem.signal_ss()
        diag = diagnostics(problem, model, ev)
        fits = []
        for name in remaining:
            t0 = time.monotonic()
            f = FITTERS[name](problem, model, recs)
            dbic = n_eff * math.log(ev.ssr / max(f.ssr, 1e-30)) - f.n_params * math.log(n_eff)
            frac = (ev.ssr - f.ssr) / max(ev.ssr - noise_ss, 1e-30)
            fits.append((f, dbic, frac))
            ana.candidates_tried.append({"step": len(ana.steps) + 1, "effect": name,
                                         "params": _jsonable(f.params),
                                         "gap": _gap(problem, f.ssr), "delta_bic": dbic,
                                         "excess_explained": frac, "unobservable": f.unobservable})
            say(f"  {name:16s} gap {_gap(problem, f.ssr):.4f}  explains {100 * frac:5.1f} % of the excess  "
                f"ΔBIC {dbic:9.1f}  {_fmt_params(f.params)}  ({time.monotonic() - t0:.1f} s)")
        ok = [x for x in fits if x[0].n_params > 0 and x[1] > bic_min and x[2] >= min_explained
              and ev.ssr - x[0].ssr >= min_gain]
        if not ok:
            say("  no candidate is significant")
            break
        best, dbic, frac = max(ok, key=lambda x: x[2])
        model = best.model
        gap_before = _gap(problem, ev.ssr)
        problem.refresh(model, fpn=fpn)
        if fpn:
            # The FPN estimate under the old model absorbed part of this effect: refit once with the new one.
            ref = FITTERS[best.effect](problem, model, recs)
            if ref.ssr < problem.evaluate(model).ssr:
                best = FitResult(best.effect, ref.model, _merge_params(best.effect, nominal, ref.model),
                                 ref.ssr,
                                 ref.unobservable, ref.n_params)
                model = best.model
                problem.refresh(model, fpn=fpn)
        # Effects named earlier absorbed part of this one: refit each once with it in the model.
        for st in ana.steps:
            f = FITTERS[st["effect"]](problem, model, recs)
            if f.ssr < problem.evaluate(model).ssr:
                model = f.model
                st["params"] = _jsonable(_merge_params(st["effect"], nominal, model))
                problem.refresh(model, fpn=fpn)
                say(f"  refit {st['effect']}: {_fmt_params(st['params'])}")
        ev = problem.evaluate(model, keep=True)
        gap_after = _gap(problem, ev.ssr)
        ana.steps.append({"effect": best.effect, "params": _jsonable(best.params), "gap_before": gap_before,
                          "gap_after": gap_after, "delta_bic": dbic, "excess_explained": frac,
                          "n_params": best.n_params, "unobservable": best.unobservable,
                          "diagnostic": DIAGNOSTIC_FOR[best.effect],
                          "centroid_lag_median_s": diag["lag_median_s"]})
        if best.unobservable:
            ana.unobservable[best.effect] = best.unobservable
        ana.diags.append((best.effect, diag))
        ana.snapshots.append((best.effect, _mean_residual_map(ev, problem), gap_after))
        floor_now = math.sqrt(problem.noise_ss() / max(problem.signal_ss(), 1e-30))
        ana.gaps.append((best.effect, gap_after, floor_now))
        say(f"→ {best.effect}: {_fmt_params(best.params)}; gap {gap_before:.4f} → {gap_after:.4f}")
        remaining.remove(best.effect)
    if polish and len(ana.steps) > 1:
        # Effects found early absorbed part of the later ones: refit each named effect once more.
        for st in ana.steps:
            f = FITTERS[st["effect"]](problem, model, recs)
            if f.ssr < ev.ssr:
                model = f.model
                problem.refresh(model, fpn=fpn)
                ev = problem.evaluate(model, keep=True)
                st["params"] = _jsonable(f.params)
                say(f"  refit {st['effect']}: {_fmt_params(f.params)}; gap {_gap(problem, ev.ssr):.4f}")
    ana.model = model
    for st in ana.steps:     # report every named effect's final value (refits may have moved it)
        st["params"] = _jsonable(_merge_params(st["effect"], nominal, model))
    ana.gap_final = _gap(problem, ev.ssr)
    ana.noise_floor = math.sqrt(problem.noise_ss() / max(problem.signal_ss(), 1e-30))
    ana.unexplained = bool(ev.ssr > allowance(unexplained_excess, model_tol))
    if ana.steps:
        ana.steps[-1]["gap_after"] = ana.gap_final
    say(f"final gap {ana.gap_final:.4f} (noise floor {ana.noise_floor:.4f}); "
        + ("remaining residual is structured but no candidate explains it: UNEXPLAINED" if ana.unexplained
           else "residual at the noise level"))
    ana.seconds = time.monotonic() - t_start
    return ana


def _merge_params(effect: str, nominal: Model, model: Model) -> dict:
    """The effect's parameters as they stand in `model` (misalignment: relative to the nominal R)."""
    c, c0 = model.calib, nominal.calib
    if effect == "time_offset":
        return {"time_offset_s": c.time_offset_s}
    if effect == "rolling_readout":
        return {"readout_s": c.readout_s, "time_offset_s": c.time_offset_s}
    if effect == "gyro_bias":
        return {"bias_rad_s": list(c.bias_rad_s)}
    if effect == "gyro_scale":
        return {"scale": list(c.scale)}
    if effect == "misalignment":
        return {"rotvec_rad": so3_log(c.R_cam_gyro_matrix @ c0.R_cam_gyro_matrix.T).tolist()}
    if effect == "time_constant":
        return {"tau_s": c.tau_s}
    return {"psf_sigma_px": model.final_calibration().psf_sigma_px, "extra_sigma_px": model.extra_psf_px}


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def _fmt_params(p: dict) -> str:
    out = []
    for k, v in p.items():
        if isinstance(v, (list, tuple)):
            out.append(f"{k}=[{', '.join(f'{x:.4g}' for x in v)}]")
        else:
            out.append(f"{k}={v:.4g}")
    return " ".join(out)


# ----------------------------------------------------------------------------------------- outputs
def calibration_toml(calib: Calibration) -> str:
    """`[calibration]` table with the recording attribute names (ready for `thermod run --config`)."""
    lines = ["# written by `thermod discrepancy`: the model the recordings support", "[calibration]"]
    for k, v in calib.as_dict().items():
        if k in ("width", "height"):
            lines.append(f"{k} = {int(v)}")
        elif isinstance(v, list) and v and isinstance(v[0], list):
            rows = ("[" + ", ".join(repr(float(x)) for x in row) + "]" for row in v)
            lines.append(f"{k} = [" + ", ".join(rows)
                         + "]")
        elif isinstance(v, list):
            lines.append(f"{k} = [" + ", ".join(repr(float(x)) for x in v) + "]")
        else:
            lines.append(f"{k} = {float(v)!r}")
    return "\n".join(lines) + "\n"


def replace_calibration_table(text: str, calib: Calibration) -> str:
    """`text` (a thermod TOML) with its [calibration] table replaced by `calib` (appended if absent)."""
    table = calibration_toml(calib).split("\n", 1)[1]          # drop the header comment
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if ln.split("#")[0].strip() == "[calibration]"), None)
    if start is None:
        return text.rstrip("\n") + "\n\n" + table
    end = next((i for i in range(start + 1, len(lines)) if lines[i].lstrip().startswith("[")), len(lines))
    return "".join(lines[:start]) + table + ("\n" if end < len(lines) else "") + "".join(lines[end:])


def _figures(ana: Analysis, out: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    # residual maps (RMS over the motion frames of the first recording), before/after each step
    n = len(ana.snapshots)
    vmax = max(float(np.percentile(s[1], 99)) for s in ana.snapshots) or 1.0
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.2), squeeze=False)
    for ax, (label, img, gap) in zip(axes[0], ana.snapshots, strict=True):
        im = ax.imshow(img, cmap="magma", vmin=0, vmax=vmax)
        ax.set_title(f"{'after ' + label if label != 'nominal' else 'nominal'}\ngap {gap:.4f}", fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="residual RMS (counts)")
    fig.savefig(out / "residual_maps.png", dpi=90)
    plt.close(fig)
    files.append("residual_maps.png")
    # gap per step
    fig, ax = plt.subplots(figsize=(5, 3.2))
    labels = [g[0] for g in ana.gaps]
    ax.plot(range(len(labels)), [g[1] for g in ana.gaps], "o-", label="gap")
    ax.plot(range(len(labels)), [g[2] for g in ana.gaps], "k--", label="noise floor")
    ax.set_xticks(range(len(labels)), labels, rotation=20, fontsize=8)
    ax.set_ylabel("gap (residual / motion signal)")
    ax.set_ylim(bottom=0)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "gap_per_step.png", dpi=90)
    plt.close(fig)
    files.append("gap_per_step.png")
    for i, (effect, dg) in enumerate(ana.diags):
        name = f"diagnostics_step{i + 1}_{effect}.png"
        _diag_figure(dg, DIAGNOSTIC_FOR[effect], f"before step {i + 1}: {effect}", out / name)
        files.append(name)
    return files


def _diag_figure(dg: dict, highlight: str, title: str, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    ax = axes.ravel()
    panels = {}
    ax[0].plot(dg["row_gap"], lw=1)
    ax[0].set(xlabel="image row (working res.)", ylabel="gap", title="gap vs row (rolling readout)")
    panels["row"] = ax[0]
    ax[1].plot(dg["t"], dg["frame_gap"], "o-", ms=3)
    ax[1].set(xlabel="time since motion onset (s)", ylabel="gap", title="gap vs time (bias drift)")
    panels["time"] = ax[1]
    ax[2].plot(dg["speed_deg_s"], dg["frame_gap"], "o", ms=3)
    ax[2].set(xlabel="|ω| (°/s)", ylabel="gap", title="vs angular rate (scale, misalignment)")
    panels["rate"] = ax[2]
    ax[3].plot(dg["accel_deg_s2"], dg["frame_gap"], "o", ms=3)
    ax[3].set(xlabel="|dω/dt| (°/s²)", ylabel="gap", title="vs angular acceleration (τ)")
    panels["accel"] = ax[3]
    ax[4].semilogy(dg["spectrum_freq"], dg["spectrum"], "o-", label="residual")
    ax[4].axhline(max(dg["spectrum_noise"], 1e-12), color="k", ls="--", lw=0.8, label="white noise")
    ax[4].set(xlabel="spatial frequency (cycles/px)", ylabel="power", title="residual spectrum (PSF)")
    ax[4].legend(fontsize=8)
    panels["spectrum"] = ax[4]
    ax[5].plot(dg["t"], np.asarray(dg["lag_s"]) * 1e3, "o", ms=3)
    ax[5].axhline(0, color="k", lw=0.8)
    ax[5].set(xlabel="time since motion onset (s)", ylabel="lag (ms)",
              title=f"kernel-centroid lag (median {dg['lag_median_s'] * 1e3:.2f} ms)")
    panels["lag"] = ax[5]
    for k, a in panels.items():
        if k == highlight:
            for s in a.spines.values():
                s.set_color("red")
                s.set_linewidth(2.5)
    fig.suptitle(title + f"  (red: the diagnostic for {highlight})")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_report(ana: Analysis, out: str | Path, inputs: list[str], config_text: str | None = None) -> dict:
    """DIR/report.json, report.md, model.toml and the figures; returns the JSON report.

    model.toml is `config_text` (a full thermod configuration; default: the packaged simulated-payload
    configuration) with its [calibration] table replaced, so it is ready for `thermod run --config`
    as well as `thermod deblur --config` (which reads only the table).
    """
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out {out}: cannot create the output directory ({e.strerror})") from None
    rep = _jsonable(ana.report())
    rep["inputs"] = [str(p) for p in inputs]
    (out / "report.json").write_text(json.dumps(rep, indent=2, allow_nan=True) + "\n")
    final = ana.model.final_calibration()
    if config_text is None:
        from thermod.runtime.config import default_path
        config_text = default_path().read_text()
    (out / "model.toml").write_text(replace_calibration_table(config_text, final))
    figs = _figures(ana, out)
    md = ["# thermod discrepancy report", "", f"Inputs: {', '.join(rep['inputs'])}", "",
          f"- gap: {ana.gap_initial:.4f} (nominal) → {ana.gap_final:.4f} (final); "
          f"noise floor {ana.noise_floor:.4f}",
          "- gap = ‖measured − predicted‖ / ‖measured − static reference‖ over valid pixels of the "
          "motion frames",
          f"- unexplained structure left: **{'yes' if ana.unexplained else 'no'}**", "",
          "| step | effect | parameters | gap before | gap after | ΔBIC | excess explained |",
          "|---|---|---|---|---|---|---|"]
    for i, s in enumerate(ana.steps, 1):
        md.append(f"| {i} | {s['effect']} | {_fmt_params(s['params'])} | {s['gap_before']:.4f} | "
                  f"{s['gap_after']:.4f} | {s['delta_bic']:.0f} | {100 * s['excess_explained']:.0f} % |")
    if not ana.steps:
        md.append("| – | nothing added | | | | | |")
    md += ["", "Notes:", "",
           "- The reference is the mean of the static frames, so it already carries the optics' PSF and the "
           "fixed-pattern noise: a PSF shared by static and moving frames leaves no gap and cannot be "
           "estimated here; `optical_psf` fits only blur that the moving frames have *in addition*.",
           "- FPN is estimated as the high-passed temporal mean of the motion residual (it stays on the "
           "sensor while the scene moves) and added back to every prediction.",
           "- A gyro bias hypothesis uses the static segment's mean raw rate as a prior (the camera is "
           "still there), refined by the images."]
    if ana.unobservable:
        md += ["", "Not observable with this motion (left at their previous values):"]
        md += [f"- {k}: {', '.join(v)}" for k, v in ana.unobservable.items()]
    md += ["", "## Candidates tried", "", "| step | effect | gap | ΔBIC | excess explained | parameters |",
           "|---|---|---|---|---|---|"]
    for c in ana.candidates_tried:
        md.append(f"| {c['step']} | {c['effect']} | {c['gap']:.4f} | {c['delta_bic']:.0f} | "
                  f"{100 * c['excess_explained']:.0f} % | {_fmt_params(c['params'])} |")
    md += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figs]
    md += ["", "The updated model is in `model.toml` (`thermod run --config model.toml`, `thermod deblur`).",
           ""]
    (out / "report.md").write_text("\n".join(md))
    return rep
