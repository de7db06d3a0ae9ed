"""Model-discrepancy workflow: which effect is missing from the calibration, and how large is it?

`thermod discrepancy REC.h5 [REC2.h5 …] --out DIR [--config model.toml]`

A recording made by the payload starts with a static segment (the gyro reads ≈ its bias) followed
by motion (or is motion only: see below). The workflow

1. builds a **reference scene** from the static frames (their mean: the detector is settled and the
   camera still, so this is the sharp view, with the static optical PSF and the fixed-pattern noise);
2. **predicts** every motion frame from the reference, the raw gyro and the current model with
   `thermod.calib.forward.ForwardModel` (Eq. 16 homographies, Eq. 10/11 thermal IIR at sub-pixel steps,
   rolling readout, extra Gaussian PSF) at a reduced working resolution;
3. measures the **gap**: ``gap = ‖measured − predicted‖ / ‖measured − reference‖`` over the pixels
   valid in every view (1 = the model explains nothing of the motion signal, 0 = everything), with
   the **noise floor** the gap a perfect model would leave, from the static frames' temporal noise;
4. fits each **candidate effect** (time_offset, rolling_readout, gyro_bias, gyro_scale,
   misalignment, time_constant, optical_psf, the gyro-side clock_drift, gyro_lowpass,
   gyro_saturation, and the detector-side detector_nonlinearity and ffc_event of `sensor`): coarse
   search, then bounded refinement. A candidate is
   accepted only if its BIC gain on *effective* independent residual samples (pixel correlation
   measured from the residual's autocorrelation) is decisive and it removes a sizeable fraction of
   the gap's excess over the noise floor; the best one is added to the model, the effects named
   before it are refitted with it in place (they may have absorbed part of it), and the loop repeats;
   the gyro bias also uses the static segment's mean raw rate as a prior (a direct measurement);
5. says ``unexplained: true`` when the remaining residual is still well above the noise floor but no
   candidate explains it, rather than naming a wrong effect (``unexplained_reason`` says why).

The noise variance never falls below the counts' quantisation at the working resolution (scale²/12
counts²): identical static frames (a noiseless render) would otherwise give a floor of 0.

**Readout and offset.** Row r is read T_ro·(1 − (r+1)/H) before the frame time: a readout delays the
rows by T_ro/2 on average, as an offset does, plus a part that grows down the frame, which only a
readout makes. An offset of −T_ro/2 cancels the mean delay and leaves only the row-dependent part, so
the readout is fitted both with the offset held and with the mean row timing kept (the offset moved by
−ΔT_ro/2); the second, when decisively better, moves the offset, and `time_offset` is named with it
(`Effect.implies`). The step's readout fit also says when the motion cannot separate the two (their
Jacobian columns correlate above 0.98, or neither moves the frames): only offset − T_ro/2 is known then.

**Motion only.** A recording without a static lead-in (fewer than 3 frames before the gyro sees motion)
gets a motion-only reference instead (report: ``"reference": "motion"``): a scene canvas S, somewhat
larger than the frame where the motion needs it, in the camera frame at t_ref (the frame whose
preceding 5τ moved least). S starts as the frames back-projected and averaged (a blurred mosaic) with
the t_ref frame on top, and is refined by a few Jacobi-preconditioned CGLS iterations of
min Σ (M − F − A S)² (the forward model A is linear in S; `ForwardModel.adjoint` is Aᵀ), alternating
with the FPN estimate once per step in `Problem.refresh` — never inside a candidate's fit. S is shared
by every frame, so it cannot follow an error that differs from frame to frame (every candidate effect
moves or blurs each frame according to its own motion); canvas pixels seen by fewer than 2.5 frames
are left out so no frame predicts what only it saw. Estimated under the current, wrong model, S still
absorbs part of the missing effect (a 6 ms offset was fitted at 3.2 ms, and half its gap stayed), so the
best few candidates (up to three, explaining ≥ ¼ of what the best does) are refitted on their SSR
minimised over S too, from a canvas rebuilt under each one's first fit (`projection`: Levenberg–
Marquardt steps whose Jacobian has the share a canvas change could explain projected out, with the
canvas moving along; the current model's canvas gets as much refinement as the baseline). Once an
effect is named, the named effects are refitted in turn the same way until the SSR drops by less than
2 % a round (at most 6): on a three-axis flight a 4 % scale error ends at (1.040, 0.970, 1.048) for
(1.04, 0.97, 1.05), where alternating S and local refits ended at (1.031, 0.986, 0.966), and a
roll-axis bias of 0.015 rad/s at 0.01495 rather than 0.0213. Flat-field
corrections in the model are honoured there as in the static path: frozen frames are left out of S
and of the FPN, and each segment after an event has its own FPN. There is no static segment to
measure the noise: it is the spatial high-pass (Immerkær) of the motion residual, an upper bound while
model errors remain (``noise_source`` says which estimate was used; at a working scale of ½ the
forward model's own resampling error dominates it: 9.5 counts² on a clean 320×240 flight against the
simulator's 1.0); there is no static bias prior either.

Fixed-pattern noise (FPN) sits still on the sensor while the scene moves, so it is estimated as the
temporal mean of the motion residual and added back to every prediction (and removed from the
reference before warping). The optical PSF of the static frames is in the reference already: the
`optical_psf` candidate fits the *extra* blur σ_e of motion frames and reports the model's Eq. 19 σ
as √(σ_nominal² + σ_e²) (the static blur is taken to be the nominal one). A PSF that static and
moving frames share is therefore *unobservable* from this comparison — the workflow leaves it alone.
Parameters the motion does not excite (a gyro axis that barely turns; misalignment directions about
the only rotation axis) are not fitted and are listed under `unobservable`. Flat-field steps, fitted
first as the difference of the mean residuals after and before an event, are refined on the projected
cost without a static reference (a canvas made without the step takes it in).

The gyro-side effects compete with simpler ones: a clock drift (a line: offset at an epoch plus
ε) and a DLPF (a delay at low frequencies) are named only if they beat the best pure time offset,
fitted on the same footing (both on the step's canvas, or both projected), decisively
(`Effect.simpler`), so with motion that lacks the content to tell them apart the report names the simpler
`time_offset`. Saturation reads the range off the raw samples (a pile-up at a constant |rate|) and
fits only the amplitude of the clipped runs' continuation: one gain, or for one recording a gain per
run when that is decisively better (the guessed shape of a long run is off by more than a short one's).
Parameters the motion does not excite are judged by the rate that shows them (a scale axis by its own
rate, a misalignment direction by the rate across it: ≥ 2 °/s RMS and ≥ 0.2 % of the information),
not by their share of it.

The forward model's own precision (resampling at the working resolution, ≈ 1–5 % of the motion
signal on simulator data; 2.2–2.4 % above the noise floor on clean flight recordings) is allowed for
by `model_tol` (0.05): candidates are searched while the gap exceeds the noise by more than ½·model_tol
of the signal, and a candidate must remove at least that much ((½·model_tol)²·‖signal‖² of SSR);
what is left counts as unexplained only above the full model_tol.

After the last step, a **backward elimination** drops an effect the later ones made redundant: reset
to nominal, the SSR rises by less than a candidate must remove (or not decisively by BIC). A time
offset named before the DLPF whose group delay it stood for ends at ≈ 0 and is dropped (the report
lists it under "dropped").

A curved detector response is nearly taken in by a motion-only canvas (solved in linear counts under
a response model: A X ≈ L(M − F), S = L⁻¹(X)); the gap barely moves, but the residual keeps a one-sign
trace where the blur mixes levels (`diagnostics.response_signature`: its regression on P(r²) − P(r)²).
When that trace is significant (|z| > 6) and large (an apparent gain change > 4 % over ±3 RMS contrast;
the forward model's own trace on a clean high-contrast flight is 3.3 %), the result is `unexplained`.

Without a static reference a blur every frame shares is part of the estimated scene (a Gaussian PSF
commutes with the frames' shifts, rotations and the thermal IIR), so `optical_psf` is reported
unobservable on motion-only recordings rather than fitted to resampling error.

Layout: `data` (model, recording preparation, size guards), `sensor` (detector-side effects: the
response curve, flat-field corrections, the one prediction every cost goes through), `problem` (cost,
noise, step context), `effects` (one `Effect` record per candidate), `diagnostics`, `analysis` (the search),
`report` (outputs).

Outputs: DIR/report.json, DIR/report.md, DIR/model.toml and PNG figures (residual maps before and
after every step, gap per step, the diagnostic panel that pointed at each effect).
"""

from thermod.calib.discrepancy.analysis import Analysis, Candidate, Criteria, analyse
from thermod.calib.discrepancy.data import MAX_GYRO_RATE_RAD_S, Model, RecData, detect_static, prepare
from thermod.calib.discrepancy.diagnostics import diagnostics
from thermod.calib.discrepancy.effects import (
    CANDIDATES,
    EFFECTS,
    Effect,
    FitResult,
    fit_gyro_bias,
    fit_optical_psf,
    static_bias_prior,
)
from thermod.calib.discrepancy.problem import Evaluation, Problem, StepContext, effective_area
from thermod.calib.discrepancy.report import (
    calibration_toml,
    format_params,
    replace_calibration_table,
    write_report,
)

__all__ = ["CANDIDATES", "EFFECTS", "MAX_GYRO_RATE_RAD_S", "Analysis", "Candidate", "Criteria", "Effect",
           "Evaluation", "FitResult", "Model", "Problem", "RecData", "StepContext", "analyse",
           "calibration_toml", "detect_static", "diagnostics", "effective_area", "fit_gyro_bias",
           "fit_optical_psf", "format_params", "prepare", "replace_calibration_table", "static_bias_prior",
           "write_report"]
