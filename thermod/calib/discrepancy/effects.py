"""The candidate effects, one `Effect` record each: its fit, the diagnostic panel that points at it,
the calibration fields it owns and how its values read from a model (its merge into the calibration).

Every fit takes the step's `StepContext` and the current `Model` and returns a `FitResult` whose
model has the effect merged in: a coarse search, then a bounded refinement.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from thermod.calib.discrepancy import sensor
from thermod.calib.discrepancy.data import Model
from thermod.calib.discrepancy.fitting import current_ssr, scalar_fit, vector_fit, with_calib
from thermod.calib.discrepancy.problem import StepContext
from thermod.physics.calibration import RANGES
from thermod.physics.effects import EFFECTS as VOCABULARY
from thermod.physics.geometry import so3_log
from thermod.physics.gyro_effects import continuations, detect_clip_level, group_delay_s
from thermod.physics.kernels.grids import kernel_span_s


@dataclass
class FitResult:
    effect: str
    model: Model
    ssr: float
    unobservable: list = field(default_factory=list)
    n_params: int = 1


@dataclass(frozen=True)
class Effect:
    """One candidate effect.

    fit(ctx, model) -> FitResult: the model with the effect fitted in.
    diagnostic: the panel of `diagnostics` that shows it (the figure highlights it).
    fields: the `Model` (or its calibration's) fields it changes (`without` resets them).
    values(model, nominal) -> dict: its parameters as they stand in `model` (what the report says
    and what goes into model.toml), relative to `nominal` where the field composes (misalignment).
    simpler: the effect it generalises ("" if none): it is named only when it beats that one
    decisively (`analysis._beats_simpler`), so a clock line or a DLPF that acts as a plain delay is
    reported as the time offset it amounts to.
    implies: effects whose fields its fit may move, and only where the data demand it (the readout's
    centred fit moves the time offset): when the fit that is named moved them, they are named with it.
    collapse(model) -> Model | None: `model` with this effect's most flexible parameters folded into
    fewer (per-run gains into one), None when there is nothing to fold. Flexible parameters absorb
    an effect that is named after them; the refit restarts from the folded model to get out.
    """

    name: str
    fit: Callable[[StepContext, Model], FitResult]
    diagnostic: str
    fields: tuple[str, ...]
    values: Callable[[Model, Model], dict]
    simpler: str = ""
    implies: tuple[str, ...] = ()
    collapse: Callable[[Model], Model | None] | None = None

    def without(self, model: Model, nominal: Model) -> Model:
        """`model` with every field this effect owns put back to `nominal`'s value."""
        own = {f.name for f in dataclasses.fields(Model)}
        m = dataclasses.replace(model, **{f: getattr(nominal, f) for f in self.fields if f in own})
        cal = {f: getattr(nominal.calib, f) for f in self.fields if f not in own}
        return dataclasses.replace(m, calib=dataclasses.replace(m.calib, **cal)) if cal else m


# ----------------------------------------------------------------------------------------- fits
def fit_time_offset(ctx: StepContext, model: Model, max_offset_s: float = 0.03) -> FitResult:
    """Constant gyro → camera clock offset."""
    t0 = model.calib.time_offset_s
    grid = t0 + np.arange(-max_offset_s, max_offset_s + 1e-9, 0.005)
    # the search stays inside the range a Calibration accepts (a model at its end searches one way)
    lo_r, hi_r = RANGES["time_offset_s"][:2]
    grid = grid[(grid >= lo_r) & (grid <= hi_r)]

    def make(x):
        return with_calib(model, time_offset_s=float(x))
    x, ssr = scalar_fit(ctx, make, grid, max(t0 - max_offset_s, lo_r), min(t0 + max_offset_s, hi_r), 0.005,
                        x0=t0)
    return FitResult("time_offset", make(x), ssr)


def fit_rolling_readout(ctx: StepContext, model: Model) -> FitResult:
    """Readout time T_ro ∈ [0, frame period]. Row r is read T_ro·(1 − (r+1)/H) before the frame time, so
    a readout delays the rows by T_ro/2 on average (what a time offset does too) plus a part that grows
    down the frame (what only a readout does). Two one-parameter families are fitted: T_ro with the
    offset held (the mean delay comes with it), and T_ro with the offset moved by −ΔT_ro/2 (the mean
    timing kept, only the row-dependent part changes: `make_centred`). The centred one is kept when it
    fits better, and before a time offset is named only when decisively so (`_fit_keeping_timing`): an
    offset of −T_ro/2 cancels the readout's mean delay (a −5 ms offset beside a 10 ms readout leaves only
    the row-dependent part, which the held-offset family fits at 2 ms), and the offset it moves is then
    a second effect the data show (`Effect.implies`). On the step's own fit (neither warm nor projected)
    the result says whether the motion separates readout and offset at all (`timing_separation`)."""
    c0 = model.calib
    hi = 1.0 / c0.frame_rate_hz
    grid = np.linspace(0.0, hi, 11)

    def make(x):
        return with_calib(model, readout_s=float(x))

    def make_centred(x):
        offset = c0.time_offset_s - 0.5 * (float(x) - c0.readout_s)
        return with_calib(model, readout_s=float(x), time_offset_s=offset)

    f = _fit_keeping_timing(ctx, "rolling_readout", make, make_centred, grid, 0.0, hi, x0=c0.readout_s,
                            before_offset=True)
    if not ctx.warm and not ctx.project:
        note = timing_separation(ctx, f.model)
        if note:
            f.unobservable.append(note)
    return f


def _fit_keeping_timing(ctx: StepContext, name: str, make, make_centred, grid, lo: float, hi: float,
                        x0=None, before_offset: bool = False):
    """`make(x)` fitted, and `make_centred(x)`, which moves this effect's mean timing shift out of the
    time offset: the better fit. Once `time_offset` is in the model the offset is a parameter already
    (it may have absorbed that shift); before (only with `before_offset`), moving it is one parameter
    more, so the centred fit must win decisively (ΔBIC > 10 for it and at least `min_gain` of SSR)."""
    x, ssr = scalar_fit(ctx, make, grid, lo, hi, None, x0=x0)
    best = FitResult(name, make(x), ssr)
    named = "time_offset" in ctx.named
    if named or (before_offset and not ctx.warm):     # a refit does not move an offset nobody named
        xc, ssrc = scalar_fit(ctx, make_centred, grid, lo, hi, None, x0=x0)
        if ssrc < ssr and (named or (ctx.delta_bic(ssr, ssrc, 1) > 10.0 and ssr - ssrc >= ctx.min_gain)):
            best = FitResult(name, make_centred(xc), ssrc)
    return best


# Readout and offset count as not separated when their estimates correlate more than this.
MAX_TIMING_CORRELATION = 0.98


def timing_separation(ctx: StepContext, model: Model, h_s: float = 0.002) -> str:
    """Whether the motion separates a rolling readout from a time offset about `model`: their Jacobian
    columns (the frames' change per second of offset, and per second of readout with the mean row
    timing held: the row-dependent part) on the masked pixels give the 2×2 information matrix; its
    correlation says how far the two estimates trade off. An empty string when they are separated,
    else a note that only the mean row delay (offset − T_ro/2) is determined. Image motion along the
    rows' read order is what separates them; motion that is too slow, or too uniform in time to tell a
    row's delay from the frame's, does not."""
    c = model.calib
    base = ctx.problem.residual_vector(model)
    j_off = (ctx.problem.residual_vector(with_calib(model, time_offset_s=c.time_offset_s + h_s)) - base) / h_s
    sign = -1.0 if c.readout_s + h_s > 1.0 / c.frame_rate_hz else 1.0
    t_ro = c.readout_s + sign * h_s
    j_row = (ctx.problem.residual_vector(with_calib(model, readout_s=t_ro, time_offset_s=c.time_offset_s
                                               - 0.5 * sign * h_s)) - base) / (sign * h_s)
    j_ro = j_row + 0.5 * j_off            # readout with the offset held: the row part plus half a delay
    a, b, d = float(j_off @ j_off), float(j_off @ j_ro), float(j_ro @ j_ro)
    if min(a, d) * 1e-6 < ctx.chi2_scale:     # 1 ms of either changes the SSR by less than one χ² unit
        return "rolling_readout vs time_offset: the frames do not move with either (no image motion)"
    rho = b / math.sqrt(a * d)
    if abs(rho) <= MAX_TIMING_CORRELATION:
        return ""
    return (f"rolling_readout vs time_offset: the motion cannot separate them (their estimates correlate "
            f"{rho:.3f}): only the mean row delay, offset − readout/2 = "
            f"{1e3 * (c.time_offset_s - 0.5 * c.readout_s):.2f} ms, is determined")


def fit_time_constant(ctx: StepContext, model: Model) -> FitResult:
    tau = model.calib.tau_s
    # ×/÷ 3 about the model, inside the range a Calibration accepts
    lo = math.log(max(tau / 3.0, RANGES["tau_s"][0]))
    hi = math.log(min(tau * 3.0, RANGES["tau_s"][1]))

    def make(x):
        return with_calib(model, tau_s=float(math.exp(x)))
    x, ssr = scalar_fit(ctx, make, np.linspace(lo, hi, 13), lo, hi, None, x0=math.log(tau))
    return FitResult("time_constant", make(x), ssr)


def fit_optical_psf(ctx: StepContext, model: Model, max_sigma_px: float = 3.0) -> FitResult:
    """Extra Gaussian blur σ_e of the motion frames beyond the static ones (adds in quadrature).

    Without a static reference there is nothing to be extra to: a Gaussian blur shared by every frame
    commutes with their motion (shifts and rotations) and with the thermal IIR, so the estimated scene
    takes it whole, and the fit would only chase the forward model's resampling error."""
    if not any(d.reference == "static" for d in ctx.recs):
        return FitResult("optical_psf", model, ctx.problem.evaluate(model).ssr, n_params=0, unobservable=[
            "optical_psf: no static reference; a blur common to every frame is part of the estimated scene"])

    def make(x):
        return dataclasses.replace(model, extra_psf_px=float(math.hypot(model.extra_psf_px, x)))
    x, ssr = scalar_fit(ctx, make, np.linspace(0.0, max_sigma_px, 13), 0.0, max_sigma_px, None)
    return FitResult("optical_psf", make(x), ssr)


# A parameter shows in the images through a rate: below this RMS (and below this share of the strongest
# direction's information) a gyro axis or a misalignment direction is listed unobservable, not fitted.
MIN_EXCITATION_RAD_S = math.radians(2.0)
MIN_INFORMATION_SHARE = 0.002


def _axis_observable(recs, min_rms: float = MIN_EXCITATION_RAD_S, min_share: float = MIN_INFORMATION_SHARE):
    """Gyro axes whose motion RMS (rad/s) is ≥ min_rms (2 °/s) and whose share of the information
    (RMS²) is ≥ min_share × the strongest axis's (0.2 %: an RMS ≥ 4.5 % of it), as `fit_misalignment`
    judges directions. A scale error shows as (s − 1) ω: the axis's own rate decides, not its share.
    With a 10 % cut the real log's pitch axis from 25 s (6.8 °/s beside 118 °/s of roll) was left out and its
    4 % error named as a 0.003 rad/s gyro bias."""
    rms = np.sqrt(np.mean([d.motion_rms_rad_s**2 for d in recs], axis=0))
    return (rms >= min_rms) & (rms**2 >= min_share * rms.max() ** 2)


def static_bias_prior(ctx: StepContext, b0, unit: float, bias_stability_rad_s: float):
    """The static segments' mean raw rate as a measurement of the bias (in `unit`s relative to b0)
    with its weight on the image χ² scale, or None when no recording has a static mean."""
    sm = [d.static_gyro_mean for d in ctx.recs if d.static_gyro_mean is not None]
    if not sm:
        return None
    xs = (np.mean(sm, axis=0) - b0) / unit
    sem = [d.static_gyro_sem for d in ctx.recs if d.static_gyro_sem is not None]
    sem = np.sqrt(np.mean(np.square(sem), axis=0) / len(sem)) if sem else np.zeros(3)
    sigma = np.sqrt(sem**2 + bias_stability_rad_s**2) / unit
    return xs, ctx.chi2_scale / sigma**2


def fit_gyro_bias(ctx: StepContext, model: Model, bias_stability_rad_s: float = math.radians(0.05),
                  use_static_prior: bool = True) -> FitResult:
    """Bias: the static segment measures it directly (the camera is still, the gyro reads its bias),
    so its mean enters as a prior with its standard error ⊕ `bias_stability_rad_s` (drift between
    the static and the moving part); the images refine it. The prior's weight puts both on the
    same χ² scale: image SSR / (residual variance × pixels per independent sample)."""
    b0 = np.asarray(model.calib.bias_rad_s, float)
    unit = math.radians(0.2)
    prior = static_bias_prior(ctx, b0, unit, bias_stability_rad_s) if use_static_prior else None
    starts = [np.zeros(3)] + ([prior[0]] if prior is not None else [])

    def make(x):
        return with_calib(model, bias_rad_s=tuple(float(v) for v in b0 + x))
    x, ssr = vector_fit(ctx, make, starts, unit, bound=100.0, prior=prior)   # ±20 °/s
    return FitResult("gyro_bias", make(x), ssr, n_params=3)


def fit_gyro_scale(ctx: StepContext, model: Model, bic_min: float = 10.0) -> FitResult:
    """Scale factor: one common factor first, per-axis factors only if the BIC on effective samples
    prefers the two extra parameters (Occam: a common error is the usual case and the per-axis fit of
    a weakly excited axis, typically roll, is noisy). Axes the motion barely excites are not fitted."""
    s0 = model.calib.scale_vector
    obs = _axis_observable(ctx.recs)
    idx = np.flatnonzero(obs)
    unit = 0.01
    un = [f"scale[{a}]" for a in range(3) if not obs[a]]

    def make(x):     # one common factor when x has one element, else one per observable axis
        s = s0.copy()
        s[idx] = s0[idx] * (1.0 + np.asarray(x, float))
        return with_calib(model, scale=tuple(float(v) for v in s))

    if len(idx) == 0:
        return FitResult("gyro_scale", model, ctx.problem.evaluate(model).ssr, unobservable=un, n_params=0)
    if ctx.warm and len(idx) > 1 and np.ptp(s0[idx]) > 0:
        # a refit of per-axis factors the search chose: refined per axis (a common factor's fit first
        # would keep their ratios, and per-axis steps would have to beat it by a whole min_gain again)
        x3, ssr3 = vector_fit(ctx, make, [np.zeros(len(idx))], unit, bound=20.0)
        return FitResult("gyro_scale", make(x3), ssr3, unobservable=un, n_params=len(idx))
    x1, ssr1 = vector_fit(ctx, make, [np.zeros(1)], unit, bound=20.0)
    best = FitResult("gyro_scale", make(x1), ssr1, unobservable=un, n_params=1)
    if len(idx) > 1:
        x3, ssr3 = vector_fit(ctx, make, [np.full(len(idx), x1[0] / unit)], unit, bound=20.0)
        if ctx.delta_bic(ssr1, ssr3, len(idx) - 1) > bic_min and ssr1 - ssr3 >= ctx.min_gain:
            best = FitResult("gyro_scale", make(x3), ssr3, unobservable=un, n_params=len(idx))
    return best


def fit_misalignment(ctx: StepContext, model: Model, min_rms: float = MIN_EXCITATION_RAD_S,
                     min_rel: float = MIN_INFORMATION_SHARE) -> FitResult:
    """Extra camera-side rotation δ: ω_cam' = exp(δ) ω_cam. Only directions the motion excites are fitted:
    Δω ≈ δ × ω, whose information matrix M = Σ(|ω|² I − ω ωᵀ) is singular for single-axis motion. A
    direction v is kept when the rate across it, √(vᵀMv / N), is ≥ `min_rms` (2 °/s) and its eigenvalue is
    ≥ `min_rel` × the largest (a bounded condition number). What matters is the rate across v, not its
    share: on the real log from 12 s (pitch 72 °/s, roll 5 °/s RMS) the pitch direction holds 0.5 % of
    the information, and leaving its 0.03 rad out (the old 5 % cut) stopped the others at 77 %."""
    c0 = model.calib
    M, n = np.zeros((3, 3)), 0
    for d in ctx.recs:
        _, w = c0.gyro_to_camera(d.gyro_t, d.gyro_rate)
        w = w[d.gyro_t + c0.time_offset_s > d.t_onset]
        M += np.sum(w**2) * np.eye(3) - w.T @ w
        n += len(w)
    ev, evec = np.linalg.eigh(M)
    keep = (np.sqrt(np.maximum(ev, 0.0) / max(n, 1)) >= min_rms) & (ev >= min_rel * max(ev.max(), 1e-12))
    basis = evec[:, keep]

    def make(x):
        return dataclasses.replace(model, calib=c0.with_misalignment(basis @ np.asarray(x)))
    x, ssr = vector_fit(ctx, make, [np.zeros(basis.shape[1])], math.radians(0.5), bound=20.0)   # ±10°
    un = [f"rotation about {np.round(evec[:, i], 2).tolist()}" for i in np.flatnonzero(~keep)]
    return FitResult("misalignment", make(x), ssr, unobservable=un, n_params=int(keep.sum()))


# ----------------------------------------------------------------------------------------- registry
def _calib_values(*keys):
    def values(model: Model, nominal: Model) -> dict:
        return {k: getattr(model.calib, k) for k in keys}
    return values


def _misalignment_values(model: Model, nominal: Model) -> dict:
    R, R0 = model.calib.R_cam_gyro_matrix, nominal.calib.R_cam_gyro_matrix
    return {"rotvec_rad": so3_log(R @ R0.T).tolist()}


def _psf_values(model: Model, nominal: Model) -> dict:
    return {"psf_sigma_px": model.final_calibration().psf_sigma_px, "extra_sigma_px": model.extra_psf_px}


CAMERA_EFFECTS = (
    Effect("time_offset", fit_time_offset, "lag", ("time_offset_s",), _calib_values("time_offset_s")),
    Effect("rolling_readout", fit_rolling_readout, "row", ("readout_s", "time_offset_s"),
           _calib_values("readout_s", "time_offset_s"), implies=("time_offset",)),
    Effect("gyro_bias", fit_gyro_bias, "time", ("bias_rad_s",), _calib_values("bias_rad_s")),
    Effect("gyro_scale", fit_gyro_scale, "rate", ("scale",), _calib_values("scale")),
    Effect("misalignment", fit_misalignment, "rate", ("R_cam_gyro",), _misalignment_values),
    Effect("time_constant", fit_time_constant, "accel", ("tau_s",), _calib_values("tau_s")),
    Effect("optical_psf", fit_optical_psf, "spectrum", ("extra_psf_px",), _psf_values),
)


# ----------------------------------------------------------------------------------------- gyro-side effects
# clock_drift, gyro_lowpass, gyro_saturation (issue 12): fields of `Calibration.condition_gyro`, so the
# forward model, `thermod deblur` and the daemon all apply what is fitted here.



def fit_clock_drift(ctx: StepContext, model: Model, max_ppm: float = 20000.0) -> FitResult:
    """Gyro clock rate error ε (ppm) with the offset at its epoch: t_cam = t_gyro + offset + ε (t_gyro −
    epoch), the epoch being the gyro-clock time of the first analysed frame (or the model's own once it
    has a drift). The clock map is a line, so both are fitted; the search names it only if it beats
    the best pure time offset decisively (`Effect.simpler`). ±2 % covers an RC-clocked MEMS output
    data rate; a crystal's ±100 ppm moves a 1 s recording by ±0.1 ms, which only long recordings
    resolve."""
    c0 = model.calib
    epoch = c0.clock_epoch_s if c0.clock_drift_ppm else float(
        min(d.frame_t[0] for d in ctx.recs) - c0.time_offset_s)
    p0, off0 = c0.clock_drift_ppm, c0.time_offset_s
    unit = np.array([1e-3, 1000.0])          # 1 ms, 1000 ppm

    def make(x):
        x = np.asarray(x, float)
        ppm = float(np.clip(p0 + x[1], -max_ppm, max_ppm))
        return with_calib(model, time_offset_s=float(off0 + x[0]), clock_drift_ppm=ppm, clock_epoch_s=epoch)
    starts = [np.zeros(2)] + [np.array([0.0, s]) for s in (-4.0, 4.0)]
    x, ssr = vector_fit(ctx, make, starts, unit, bound=max_ppm / 1000.0)
    return FitResult("clock_drift", make(x), ssr, n_params=2)


def _lowpass_model(model: Model, delay_s: float, offset_s: float | None = None) -> Model:
    """The model with a 2nd-order Butterworth DLPF of DC group delay `delay_s` (0 = none)."""
    c = model.calib
    fc = group_delay_s(1.0) / delay_s if delay_s > 0 else 0.0
    fc = min(fc, 0.45 * c.rate_hz) if fc else 0.0
    changes = {"gyro_lowpass_hz": float(fc) if fc >= 1.0 else 0.0}
    if offset_s is not None:
        changes["time_offset_s"] = float(offset_s)
    return with_calib(model, **changes)


def fit_gyro_lowpass(ctx: StepContext, model: Model, max_delay_s: float = 0.03) -> FitResult:
    """The gyro chip's low-pass, parametrised by its DC group delay d = √2/(2π f_c).

    At low frequencies it is a pure delay, which `time_offset` explains as well with one parameter
    too: only its frequency dependence (attenuation 1/√(1 + (f/f_c)⁴), phase) tells it apart, so the
    search names it only if it beats the best pure time offset decisively (`Effect.simpler`). Once a
    time offset is named it has absorbed the filter's delay, so the delay is also tried moved from the
    offset into the filter (total low-frequency delay kept), as the readout fit does with its mean
    delay.
    """
    c0 = model.calib
    d0 = group_delay_s(c0.gyro_lowpass_hz) if c0.gyro_lowpass_hz else 0.0
    grid = np.linspace(0.0, max_delay_s, 13)

    def make(d):
        return _lowpass_model(model, float(d))

    def make_centred(d):
        # the delay delays the gyro: camera time of a sample = t + offset − d at low frequencies
        return _lowpass_model(model, float(d), c0.time_offset_s - d0 + float(d))

    return _fit_keeping_timing(ctx, "gyro_lowpass", make, make_centred, grid, 0.0, max_delay_s,
                               x0=d0 if d0 else None)


# Below this image shift (working px) no continuation of the clipped runs can be told from the clip.
MIN_CONTINUATION_PX = 0.1


def _run_reach_px(d, calib, runs) -> np.ndarray:
    """Per clipped run of `d` (`continuations`), an upper bound of the image shift (working px) its
    continuation at gain 1 adds to the frames: ∫|Δω| dt over the samples they integrate (5τ and the
    readout before the first frame to the last), times the larger of the focal length and the half
    diagonal (a rotation moves no pixel of the working frame by more)."""
    t_cam = np.asarray(d.gyro_t, np.float64) + calib.time_offset_s
    lo = d.frame_t[0] - kernel_span_s(calib)
    seen = (t_cam >= lo) & (t_cam <= d.frame_t[-1])
    dt = np.gradient(np.asarray(d.gyro_t, np.float64)) if len(d.gyro_t) > 1 else np.ones(len(d.gyro_t))
    intr = d.fm.intr
    focal = max(intr.fx, intr.fy, math.hypot(intr.width, intr.height) / 2.0)
    return np.array([float(np.sum((c.excess * dt[c.i0:c.i1 + 1])[seen[c.i0:c.i1 + 1]])) * focal
                     for c in runs])


def fit_gyro_saturation(ctx: StepContext, model: Model, max_gain: float = 3.0,
                        bic_min: float = 10.0) -> FitResult:
    """Clipping at the gyro's range: the range is read off the raw samples (the largest |rate| that
    samples pile up at, in runs), the clipped runs are continued smoothly (`gyro_effects.continuations`)
    and the continuation's amplitude (`gyro_clip_gain`, 1 = the cubic through the slopes on both
    sides) is fitted from the images: one gain for every run first, then (one recording) a gain per
    run if that is decisively better (ΔBIC > bic_min and min_gain more, as per-axis scale factors).
    The shape of a cut peak is only guessed, and how far it is off grows with the run: on the real
    log from 25 s a 108 ms run was continued to 1.2 × its truth and a 215 ms one to 3.4 ×; runs at an
    end of the series, known on one side only, get a gain of their own only. No pile-up: nothing to
    fit."""
    level = max(detect_clip_level(d.gyro_rate) for d in ctx.recs)
    if level <= 0:
        return FitResult("gyro_saturation", model, current_ssr(ctx, model), n_params=0,
                         unobservable=["gyro_saturation: no raw samples pile up at a constant |rate|"])
    runs = [continuations(d.gyro_t, d.gyro_rate, level) for d in ctx.recs]
    reach = [_run_reach_px(d, model.calib, r) for d, r in zip(ctx.recs, runs, strict=True)]
    top = max((float(r.max(initial=0.0)) for r in reach), default=0.0) * max_gain
    if top < MIN_CONTINUATION_PX:
        return FitResult("gyro_saturation", model, current_ssr(ctx, model), n_params=0, unobservable=[
            f"gyro_saturation: the samples at {math.degrees(level):.1f} °/s, continued at gain {max_gain:g}, "
            f"would move the frames by {top:.2g} px at most (a peak of a quantised log, or too short a "
            "clip to see)"])
    c0 = model.calib
    per_run = len(ctx.recs) == 1 and bool(np.any(reach[0] >= MIN_CONTINUATION_PX))

    def make(g):
        return with_calib(model, gyro_range_rad_s=float(level), gyro_clip_gain=float(g),
                          gyro_clip_run_gains=())
    x, ssr = scalar_fit(ctx, make, np.linspace(0.0, max_gain, 13), 0.0, max_gain, None)
    best = FitResult("gyro_saturation", make(x), ssr)
    if per_run:
        two_sided = [c.two_sided for c in runs[0]]
        each = _fit_run_gains(ctx, best.model, level, reach[0], np.where(two_sided, x, 0.0), max_gain)
        if ctx.warm and c0.gyro_clip_run_gains and c0.gyro_range_rad_s == level:
            # Refitted under a model that has since gained an effect: the gains the runs took while
            # that effect was missing (absorbing part of it) are a start, not an answer; the fresh
            # start from the common gain competes, and per-run gains must again beat one gain.
            warm = _fit_run_gains(ctx, model, level, reach[0], np.array(c0.gyro_clip_run_gains), max_gain)
            each = min(each, warm, key=lambda f: f.ssr)
        if (ctx.delta_bic(ssr, each.ssr, each.n_params - 1) > bic_min
                and ssr - each.ssr >= ctx.min_gain):
            best = each
    return best


def _fit_run_gains(ctx: StepContext, model: Model, level: float, reach: np.ndarray, g0: np.ndarray,
                   max_gain: float) -> FitResult:
    """A continuation gain per clipped run the frames see (the others keep `g0`), from `g0`, in units
    that move each run's image by ≈ 2 px."""
    seen = np.flatnonzero(reach >= MIN_CONTINUATION_PX)
    unit = 2.0 / reach[seen]

    def make(x):        # the common gain shown (and kept by `Model.final_calibration`): their median
        g = np.asarray(g0, float).copy()
        g[seen] = np.clip(g[seen] + np.asarray(x, float) * unit, 0.0, max_gain)
        return with_calib(model, gyro_range_rad_s=float(level), gyro_clip_gain=float(np.median(g[seen])),
                     gyro_clip_run_gains=tuple(float(v) for v in g))
    x, ssr = vector_fit(ctx, make, [np.zeros(len(seen))], 1.0, bound=float(np.max(max_gain / unit)))
    return FitResult("gyro_saturation", make(x), ssr, n_params=len(seen))


def _one_clip_gain(model: Model) -> Model | None:
    c = model.calib
    return with_calib(model, gyro_clip_run_gains=()) if c.gyro_clip_run_gains else None


def _lowpass_values(model: Model, nominal: Model) -> dict:
    fc = model.calib.gyro_lowpass_hz
    return {"gyro_lowpass_hz": fc, "group_delay_s": group_delay_s(fc) if fc else 0.0}


def _saturation_values(model: Model, nominal: Model) -> dict:
    c = model.calib
    out = {"gyro_range_rad_s": c.gyro_range_rad_s, "gyro_range_deg_s": math.degrees(c.gyro_range_rad_s),
           "gyro_clip_gain": c.gyro_clip_gain}
    if c.gyro_clip_run_gains:
        out["gyro_clip_run_gains"] = list(c.gyro_clip_run_gains)
    return out


GYRO_EFFECTS = (
    Effect("clock_drift", fit_clock_drift, "lag_trend",
           ("clock_drift_ppm", "clock_epoch_s", "time_offset_s"),
           _calib_values("clock_drift_ppm", "clock_epoch_s", "time_offset_s"), simpler="time_offset"),
    Effect("gyro_lowpass", fit_gyro_lowpass, "lag_freq", ("gyro_lowpass_hz", "time_offset_s"),
           _lowpass_values, simpler="time_offset"),
    Effect("gyro_saturation", fit_gyro_saturation, "clip",
           ("gyro_range_rad_s", "gyro_clip_gain", "gyro_clip_run_gains"), _saturation_values,
           collapse=_one_clip_gain),
)


# ----------------------------------------------------------------------------------------- detector side
# Effects after the thermal IIR (`sensor`): a non-linear response of the counts and flat-field corrections.
def _reference_level(recs) -> tuple[float, float]:
    """Mean level and RMS contrast (counts) of the references over the pixels the fit uses."""
    vals = np.concatenate([d.static_mean[d.mask.any(axis=0)] - (d.fpn[d.mask.any(axis=0)] if d.fpn is not None
                                                                  else 0.0) for d in recs])
    return float(vals.mean()), float(max(vals.std(), 1e-3))


def fit_detector_nonlinearity(ctx: StepContext, model: Model, max_curvature: float = 1.0) -> FitResult:
    """Curvature γ of the linearisation x = c0 + u + γu² (u = counts − c0, `sensor.Response`) about the
    references' mean level c0. γ is searched in units of 1/(3·RMS contrast): ±`max_curvature` lets the
    slope dx/dy change by up to ±2·max_curvature/3 at 3 RMS from the level (a strong non-linearity)."""
    level, spread = _reference_level(ctx.recs)
    if model.response is not None:
        level = model.response.level
    unit = 1.0 / (3.0 * spread)
    u0 = 0.0 if model.response is None else model.response.gamma / unit

    def make(u):
        return dataclasses.replace(model, response=sensor.Response(level, float(u) * unit))
    grid = u0 + np.linspace(-max_curvature, max_curvature, 21)
    x, ssr = scalar_fit(ctx, make, grid, u0 - max_curvature, u0 + max_curvature, None)
    return FitResult("detector_nonlinearity", make(x), ssr)


def fit_ffc_event(ctx: StepContext, model: Model) -> FitResult:
    """Flat-field corrections: runs of frozen motion frames (`sensor.detect_frozen`, together with the
    frames of the events already in the model), each with the global offset step of the new NUC, fitted
    as the difference of the mean residual after and before it (least squares; the per-pixel part is the
    per-segment FPN `sensor.estimate_fpn` makes once the event is in the model). No frozen run: no
    parameter. Steps of events already in the model are refitted too (the search's refit after later
    effects). A frozen frame found next to a known event lengthens it: a frame the model saw hardly
    move at first is still part of the same hold, not an event of its own."""
    here = {d.name for d in ctx.recs}
    elsewhere = [e for e in model.ffc if e.recording not in here]
    events = list(elsewhere)
    for d in ctx.recs:
        p, _ = ctx.problem.predict(model, d)
        frozen = sensor.detect_frozen(d, p, d.mask)
        for e in sensor.events_of(d, model):
            frozen |= e.frozen(d.frame_t)
        period = 1.0 / model.calib.frame_rate_hz
        for a, b in sensor.frozen_runs(frozen):
            t_end = float(d.frame_t[b]) if b < len(d.frame_t) else float(d.frame_t[-1]) + period
            events.append(sensor.FFCEvent(d.name, float(d.frame_t[a]), t_end))
    if not events:
        return FitResult("ffc_event", model, ctx.problem.evaluate(model).ssr, n_params=0)
    # every event's step is refitted: a refit after a timing effect moves the residual means
    zero = dataclasses.replace(model, ffc=tuple(dataclasses.replace(e, step_counts=0.0) for e in events))
    fitted = []
    for d in ctx.recs:
        evs = sensor.events_of(d, zero)
        if not evs:
            continue
        p, _ = ctx.problem.predict(zero, d)
        seg = sensor.segments(d, zero)
        r = np.where(d.mask, d.measured - p, np.nan)
        level = [float(np.nanmean(r[seg == s])) if np.any(seg == s) else 0.0 for s in range(len(evs) + 1)]
        fitted += [dataclasses.replace(e, step_counts=level[i + 1] - level[i]) for i, e in enumerate(evs)]
    fitted += elsewhere
    new = dataclasses.replace(model, ffc=tuple(fitted))
    if ctx.project and ctx.problem.has_motion_reference and fitted:
        new = _project_ffc_steps(ctx, new, here)
    known = {(e.recording, e.t_start, e.t_end) for e in model.ffc}
    n_new = sum((e.recording, e.t_start, e.t_end) not in known for e in fitted)
    return FitResult("ffc_event", new, ctx.problem.evaluate(new).ssr, n_params=2 * n_new)


def _project_ffc_steps(ctx: StepContext, model: Model, here: set) -> Model:
    """The steps refined on the projected cost (`projection`): a motion-only canvas estimated without a
    step takes it in wherever the views after the event see scene the views before it did not, and the
    difference of the mean residuals (the first estimate) then falls short (on the real log from 30 s,
    turning on three axes, a 20-count step was fitted at 3.4)."""
    idx = [i for i, e in enumerate(model.ffc) if e.recording in here]

    def make(x):
        ffc = list(model.ffc)
        for i, v in zip(idx, np.asarray(x, float), strict=True):
            ffc[i] = dataclasses.replace(ffc[i], step_counts=float(v))
        return dataclasses.replace(model, ffc=tuple(ffc))

    unit = 4.0      # counts: the Jacobian's step h = 1 count
    x0 = np.array([model.ffc[i].step_counts for i in idx]) / unit
    x, _ = vector_fit(ctx, make, [x0], unit, bound=float(np.max(np.abs(x0), initial=0.0)) + 1000.0)
    return make(x)


def _response_values(model: Model, nominal: Model) -> dict:
    r = model.response
    return {"level_counts": r.level if r else 0.0, "gamma_per_count": r.gamma if r else 0.0}


def _ffc_values(model: Model, nominal: Model) -> dict:
    return {"t_start_s": [e.t_start for e in model.ffc], "t_end_s": [e.t_end for e in model.ffc],
            "step_counts": [e.step_counts for e in model.ffc]}


DETECTOR_EFFECTS = (
    Effect("detector_nonlinearity", fit_detector_nonlinearity, "response", ("response",), _response_values),
    Effect("ffc_event", fit_ffc_event, "ffc", ("ffc",), _ffc_values),
)

# the vocabulary, in the order the search tries it
EFFECTS: dict[str, Effect] = {e.name: e for e in (*CAMERA_EFFECTS, *GYRO_EFFECTS, *DETECTOR_EFFECTS)}
if set(EFFECTS) - set(VOCABULARY):        # one vocabulary: every candidate is an effect of physics.effects
    raise ImportError(f"candidates missing from thermod.physics.effects: {set(EFFECTS) - set(VOCABULARY)}")
CANDIDATES = tuple(EFFECTS)


def format_resolution(resolution: dict) -> str:
    """'time_offset ±0.4 ms, …, gyro_bias ±(0.1, 0.2, 0.9) °/s, …' of `Analysis.resolution`."""
    by: dict[str, list] = {}
    for v in resolution["parameters"].values():
        by.setdefault(v["effect"], []).append(v["resolution"])
    return ", ".join(
        f"{e} ±({', '.join(f'{math.degrees(r):.2g}' for r in rs)}) °/s" if e == "gyro_bias"
        else f"{e} ±{1e3 * rs[0]:.2g} ms" for e, rs in by.items())


def format_params(p: dict) -> str:
    """An effect's parameters on one line, four significant digits each ("n/a" for a missing value)."""
    def num(x) -> str:
        return "n/a" if x is None else f"{x:.4g}"

    return " ".join(f"{k}=[{', '.join(num(x) for x in v)}]" if isinstance(v, (list, tuple))
                    else f"{k}={num(v)}" for k, v in p.items())
