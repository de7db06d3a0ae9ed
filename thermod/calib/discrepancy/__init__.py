"""Model-discrepancy workflow: which effect is missing from the calibration, and how large is it?

`thermod discrepancy REC.h5 [REC2.h5 …] --out DIR [--config model.toml]` predicts every motion frame
from a reference scene, the raw gyro and the current model (`thermod.calib.forward.ForwardModel`:
Eq. 16 homographies, the Eq. 10/11 thermal IIR at sub-pixel steps, rolling readout, extra PSF),
measures the gap ``‖measured − predicted‖ / ‖measured − reference‖`` against the noise floor, and
names, one at a time, the candidate effect that removes the most of the gap's excess decisively (BIC
on effective samples, and at least (½·model_tol)² of the signal); the effects named before are refitted
with it, a backward elimination drops those the later ones made redundant, and what no candidate
explains above the model's precision is reported ``unexplained`` rather than named wrongly.

The reference is the mean of a static lead-in, or, for a recording in motion throughout, a scene
canvas estimated from the moving frames by least squares, with the best candidates refitted on the
cost minimised over the canvas too (variable projection, `projection`). docs/design.md §8 states
every rule: the candidates, the motion-only reference, the noise floor, fixed-pattern noise, what
cannot be observed, and how an effect that generalises another must beat it.

Layout: `data` (model, preparation, size guards), `sensor` (detector-side effects, the one
prediction), `problem` (cost, noise, step context), `projection`, `fitting`, `effects` (one `Effect`
per candidate), `diagnostics`, `analysis` (the search), `identify` (the timing effects' joint test:
`ambiguous` when the motion cannot tell them apart), `report` (report.json/md, model.toml, figures).
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
    format_params,
    static_bias_prior,
)
from thermod.calib.discrepancy.problem import Evaluation, Problem, StepContext, effective_area
from thermod.calib.discrepancy.report import calibration_toml, replace_calibration_table, write_report

__all__ = ["CANDIDATES", "EFFECTS", "MAX_GYRO_RATE_RAD_S", "Analysis", "Candidate", "Criteria", "Effect",
           "Evaluation", "FitResult", "Model", "Problem", "RecData", "StepContext", "analyse",
           "calibration_toml", "detect_static", "diagnostics", "effective_area", "fit_gyro_bias",
           "fit_optical_psf", "format_params", "prepare", "replace_calibration_table", "static_bias_prior",
           "write_report"]
