"""The cost: residuals of all recordings under a candidate model over fixed per-step masks, the noise
expectation, and the per-step statistics (`StepContext`) every candidate fit is judged with."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from thermod.calib.discrepancy import sensor
from thermod.calib.discrepancy.data import Model, RecData


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

    def predict(self, model: Model, d: RecData):
        self.n_evals += 1
        return sensor.predict(d, model)

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
        """Per-step state: FPN estimate (per NUC segment: `sensor.estimate_fpn`) and the fixed valid mask.

        FPN stays put on the sensor while the scene moves, so it is what the motion residual has in
        common over time: F ← F + HP(mean_k r_k), iterated from F = 0 under the current model. Only
        its high-pass part is kept: low spatial frequencies are nearly the same in the reference and
        the moved views (so they barely matter) and would absorb slow model errors instead.
        """
        for d in self.recs:
            d.aux["ffc_fpn"] = None
            d.fpn = sensor.estimate_fpn(d, model, fpn_iters, fpn_highpass_px) if fpn else None
            d.fm.set_reference(d.static_mean, d.fpn, prescaled=True)
            _, v = sensor.predict(d, model)
            k = np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8)
            d.mask = np.stack([cv2.erode(x.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
                               for x in v]).astype(bool)

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

    def gap(self, ssr: float) -> float:
        """‖measured − predicted‖ / ‖measured − reference‖ for a residual SSR."""
        return math.sqrt(ssr / max(self.signal_ss(), 1e-30))

    def noise_floor(self) -> float:
        return self.gap(self.noise_ss())


def effective_area(residuals: list, max_lag: int = 6) -> float:
    """Σρ(d)² of the residual's spatial autocorrelation: pixels per independent sample (≥ 1).

    The variance of a sum of squares of correlated Gaussian samples is inflated by Σρ², so
    N_eff = N / Σρ² is the honest sample count for the BIC.
    """
    acc = None
    for r in residuals:
        for fr in r[:: max(1, len(r) // 6)]:
            x = fr - fr[fr != 0].mean() if np.any(fr != 0) else fr
            x = np.where(fr != 0, x, 0.0)
            F = np.fft.rfft2(x, s=(2 * x.shape[0], 2 * x.shape[1]))
            ac = np.fft.irfft2(np.abs(F) ** 2, s=(2 * x.shape[0], 2 * x.shape[1]))
            acc = ac if acc is None else acc + ac
    if acc is None or acc[0, 0] <= 0:
        return 1.0
    rho = acc / acc[0, 0]
    lags = np.r_[0:max_lag + 1, -max_lag:0]
    sub = rho[np.ix_(lags, lags)]
    return float(max(1.0, np.sum(sub**2)))


@dataclass(frozen=True)
class StepContext:
    """What one search step knows, fixed for every candidate fitted in it.

    chi2_scale: SSR of one independent χ² unit at the noise level (noise variance × pixels per
    independent sample; a wrong model must not drown priors); n_eff: effective sample count for
    the BIC; min_gain: least SSR a parameter must remove (the forward model's own imprecision);
    named: effects already in the model.
    """

    problem: Problem
    chi2_scale: float
    n_eff: float
    min_gain: float
    named: tuple[str, ...]

    @property
    def recs(self) -> list[RecData]:
        return self.problem.recs

    @classmethod
    def at(cls, problem: Problem, ev: Evaluation, named, model_tol: float) -> StepContext:
        area = effective_area(ev.residuals)
        return cls(problem, chi2_scale=problem.noise_ss() / max(ev.n, 1) * area, n_eff=ev.n / area,
                   min_gain=model_tol ** 2 * problem.signal_ss(), named=tuple(named))

    def delta_bic(self, ssr_before: float, ssr_after: float, n_params: int) -> float:
        """BIC gain on effective samples of a fit with `n_params` more parameters."""
        return self.n_eff * math.log(ssr_before / max(ssr_after, 1e-30)) - n_params * math.log(self.n_eff)
