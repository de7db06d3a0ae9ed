"""The cost: residuals of all recordings under a candidate model over fixed per-step masks, the noise
expectation, and the per-step statistics (`StepContext`) every candidate fit is judged with."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from thermod.calib.discrepancy import sensor
from thermod.calib.discrepancy.data import (
    MIN_COVERAGE,
    Model,
    RecData,
    noise_variance_spatial,
    quantisation_variance,
)


@dataclass
class Evaluation:
    ssr: float
    n: int
    residuals: list          # per recording float32 [n, h, w] (masked pixels 0)
    predicted: list


# The valid mask is fixed for a step, while candidate models move every view. A masked pixel whose
# view a candidate moves off the known scene is predicted from nothing (a residual of the size of the
# signal), which pins the search to the model the mask was made under. The margin must cover the view
# shifts of the effects searched for. A static reference is the camera's own view, entered by all
# frames alike; a motion-only scene canvas ends where fewer than MIN_COVERAGE frames saw it, an edge
# that the extreme poses of the flight reach and that moves with the model. There a 2 px margin made the
# true calibration look worse than the nominal one (pitch 41 °/s RMS, scale error 4–5 %: gap 0.0485
# against a noise floor 0.0091; 0.0128 with 5 px at work width 160, for 9 % fewer pixels). As an angle,
# so it keeps that meaning at any working resolution: 0.8° is 5 px at work width 160.
STATIC_MARGIN_PX = 2
MOTION_MARGIN_RAD = math.radians(0.8)


def mask_margin_px(d: RecData) -> int:
    """The valid mask's erosion (working px) for recording `d` (see MOTION_MARGIN_RAD)."""
    if d.reference != "motion":
        return STATIC_MARGIN_PX
    return max(STATIC_MARGIN_PX, int(round(MOTION_MARGIN_RAD * max(d.fm.intr.fx, d.fm.intr.fy))))


class Problem:
    """Residuals of all recordings under a candidate model, over fixed per-step masks."""

    def __init__(self, recs: list[RecData], scene_iters: int = 3, max_work: float = math.inf):
        self.recs = recs
        self.n_evals = 0
        self.scene_iters = scene_iters
        self._projected: list = []      # (model, state) of the last projected fits (`remember`)
        self.max_work = max_work
        self._work0 = sum(d.fm.work for d in recs)

    @property
    def work(self) -> int:
        """Forward-model pixel-steps computed since this problem was made (`ForwardModel.work`)."""
        return sum(d.fm.work for d in self.recs) - self._work0

    @property
    def exhausted(self) -> bool:
        """The work has reached `max_work`: the search takes no further phase."""
        return self.work >= self.max_work

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

    def refresh(self, model: Model, fpn: bool = True, erode_px: int | None = None, fpn_iters: int = 2,
                fpn_highpass_px: float = 1.5, keep_mask: bool = False, rebuild_scene: bool = False):
        """Per-step state: FPN estimate (per NUC segment: `sensor.estimate_fpn`) and the fixed valid mask.

        FPN stays put on the sensor while the scene moves, so it is what the motion residual has in
        common over time: F ← F + HP(mean_k r_k), iterated from F = 0 under the current model. Only
        its high-pass part is kept: low spatial frequencies are nearly the same in the reference and
        the moved views (so they barely matter) and would absorb slow model errors instead.

        Motion-only recordings also re-estimate their scene canvas here (`estimate_scene`), alternating
        with the FPN, under the current model: once per step, never inside a candidate's fit (but see
        `analysis._project_scene`). `keep_mask`: leave the valid mask as it is (SSRs stay comparable).
        `rebuild_scene`: start the canvas again from the mosaic under `model` instead of refining the one
        estimated under an older model (after a step: that one holds ghosts of the effect just found).
        `erode_px`: the valid mask's margin (default: `mask_margin_px`).
        """
        for d in self.recs:
            d.aux["ffc_fpn"] = None
            if rebuild_scene and d.reference == "motion":
                d.coverage = None
            if d.reference == "motion":
                _refresh_motion(d, model, fpn, fpn_iters, fpn_highpass_px, self.scene_iters)
            else:
                d.fpn = sensor.estimate_fpn(d, model, fpn_iters, fpn_highpass_px) if fpn else None
                d.fm.set_reference(d.static_mean, d.fpn, prescaled=True)
            if keep_mask and d.mask is not None:
                continue
            _, v = sensor.predict(d, model)
            e = mask_margin_px(d) if erode_px is None else erode_px
            k = np.ones((2 * e + 1, 2 * e + 1), np.uint8)
            d.mask = np.stack([cv2.erode(x.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
                               for x in v]).astype(bool)

    def remember(self, model: Model, keep: int = 4) -> None:
        """Keep the state (canvas, FPN) as `model`'s: a fit that tries several projected fits returns one
        of them, and its caller takes that one's canvas back with `recall`."""
        self._projected = [(m, s) for m, s in self._projected if m != model][-(keep - 1):]
        self._projected.append((model, self.state()))

    def recall(self, model: Model) -> bool:
        """Put back the state remembered for a model equal to `model`; False when there is none."""
        for m, st in reversed(self._projected):
            if m == model:
                self.restore(st)
                return True
        return False

    @property
    def has_motion_reference(self) -> bool:
        return any(d.reference == "motion" for d in self.recs)

    def state(self) -> list:
        """What `refresh` changes, per recording (`restore` puts it back)."""
        return [(d.scene, d.fpn, d.coverage, d.mask, d.static_mean, d.noise_var, d.noise_source, dict(d.aux),
                 d.fm.reference, d.fm.fpn, d.fm.support, d.fm.origin) for d in self.recs]

    def restore(self, state: list) -> None:
        for d, st in zip(self.recs, state, strict=True):
            (d.scene, d.fpn, d.coverage, d.mask, d.static_mean, d.noise_var, d.noise_source, aux,
             ref, fpn, support, origin) = st
            d.aux = dict(aux)
            d.fm.set_reference(ref, fpn, prescaled=True, origin=origin, support=support, subtract_fpn=False)

    def signal_ss(self) -> float:
        return float(sum(np.sum(((d.measured - d.static_mean) * d.mask).astype(np.float64) ** 2)
                         for d in self.recs))

    def noise_ss(self) -> float:
        """Expected SSR of a perfect model: frame noise + reference noise, minus the FPN fit's share."""
        tot = 0.0
        for d in self.recs:
            n_m = max(len(d.frame_t), 2)
            if d.reference == "motion":
                # the scene canvas is fitted to the same frames: it takes one degree of freedom per
                # known canvas pixel out of the residual (fewer when CG stops early: an upper bound);
                # every such pixel is seen MIN_COVERAGE times at least, so it takes at most that share
                n_obs = max(float(d.mask.sum()), 1.0)
                f = max(1.0 - 1.0 / MIN_COVERAGE, 1.0 - float(np.sum(d.fm.support > 0)) / n_obs)
            else:
                f = 1.0 + 1.0 / d.n_static
            f *= (1.0 - 1.0 / n_m) if d.fpn is not None else 1.0
            tot += d.noise_var * f * float(d.mask.sum())
        return tot

    def gap(self, ssr: float) -> float:
        """‖measured − predicted‖ / ‖measured − reference‖ for a residual SSR."""
        return math.sqrt(ssr / max(self.signal_ss(), 1e-30))

    def noise_floor(self) -> float:
        return self.gap(self.noise_ss())


def _refresh_motion(d: RecData, model: Model, fpn: bool, iters: int, highpass_px: float, scene_iters: int):
    """Scene canvas and FPN of a motion-only recording, alternating (the FPN moves with the sensor, the
    scene with the world; only their common part at zero motion is ambiguous, and stays in the scene).

    Flat-field corrections in the model (`sensor`) are honoured as in `sensor.estimate_fpn`: frozen frames
    say nothing about the scene or the FPN, and every segment after an event has its own offset step
    and FPN change (d.aux["ffc_fpn"], warm-started from the last refresh when the events are the same)."""
    F = d.fpn if (fpn and d.fpn is not None) else np.zeros_like(d.measured[0])
    events = sensor.events_of(d, model)
    seg = sensor.segments(d, model)
    live = seg >= 0
    prev = d.aux.get("motion_ffc_fpn")
    steps = list(prev[1]) if prev is not None and prev[0] == len(events) else [None] * len(events)

    def offsets():
        """Per frame: what the detector adds after the FPN (the events' steps and FPN changes)."""
        if not events:
            return None
        out = np.zeros_like(d.measured)
        for i, e in enumerate(events):
            after = e.after(d.frame_t)
            out[after] += np.float32(e.step_counts) + (steps[i] if steps[i] is not None else np.float32(0.0))
        return out

    first = d.coverage is None
    estimate_scene(d, model, F if fpn else None, scene_iters if first else max(2, scene_iters // 2),
                   extra=offsets(), live=live)
    if fpn:
        p, v = d.fm.predict(model.calib, model.extra_psf_px)
        p = sensor.respond(d, model, p)
        extra = offsets()
        r = np.where(v, d.measured - p - (extra if extra is not None else 0.0), 0.0)
        F = sensor.add_segment_fpn(r, v, seg, len(events) + 1, highpass_px, F, steps)
        d.fm.set_reference(d.scene, F, prescaled=True, origin=d.origin, support=d.fm.support,
                           subtract_fpn=False)
    else:
        F = None
    d.fpn = F
    d.aux["ffc_fpn"] = steps if events else None
    d.aux["motion_ffc_fpn"] = (len(events), steps)
    d.static_mean = d.fm.reference_view + (F if F is not None else 0.0)
    if d.noise_source == "spatial high-pass of the motion frames":
        # No static frames to measure the temporal noise: the residual's own spatial high frequencies
        # (scene texture mostly cancelled by the prediction), an upper bound while model errors remain.
        p, v = sensor.predict(d, model)
        r = np.where(v & live[:, None, None], d.measured - p, 0.0).astype(np.float32)
        d.noise_var = max(min(d.noise_var, noise_variance_spatial(r[live])),
                          quantisation_variance(d.fm.scale))
        d.noise_source = "spatial high-pass of the motion residual (upper bound)"


def estimate_scene(d: RecData, model: Model, fpn, iters: int, extra=None, live=None) -> None:
    """Least-squares scene canvas S of a motion-only recording under `model`: min Σ_valid (M − F − A S)²,
    A = the forward model (views, IIR, normalisation, extra PSF: linear in S), by Jacobi-preconditioned
    CGLS from the current canvas (the first time: the frames back-projected and averaged, a blurred
    mosaic, with the sharpest frame at t_ref on top). Canvas pixels seen by fewer than MIN_COVERAGE
    frames are left out (support 0), so the frames never predict what only they themselves saw.

    Under a non-linear response (`sensor.Response` L) the frames are L⁻¹(A L(S)) + F, so the canvas is
    solved for in linear counts, A X ≈ L(M − F), and S = L⁻¹(X): estimated as if linear, it would hold
    the best linear compromise, and the true response would predict worse than none.

    S is shared by every frame: it cannot follow an error that changes from frame to frame (a time
    offset, bias, scale, misalignment, τ or readout error moves or blurs each frame differently with
    its own motion), only what is common to all of them. It is re-estimated once per search step
    (`Problem.refresh`), never inside a candidate's step-canvas fit, so candidates are compared on the
    same scene (the projected fits of `projection` move it with the model).
    `extra`: per-frame offsets beyond the FPN (flat-field corrections' steps); `live`: the frames that
    see the scene (bool per frame; frozen frames of a flat-field correction do not).
    """
    fm, calib = d.fm, model.calib
    target = d.measured - (fpn if fpn is not None else 0.0) - (extra if extra is not None else 0.0)
    resp = model.response if model.response is not None and model.response.gamma != 0.0 else None
    if resp is not None:
        target = resp.linearise(target)
    first = d.coverage is None
    # coverage: how many frames (IIR weight) see each canvas pixel
    w_live = _live_weight(d, live)
    fm.set_reference(d.scene, None, prescaled=True, origin=d.origin, support=None)
    _, m_full = fm.predict_raw(calib)
    inside = (m_full >= 0.99).astype(np.float32) * w_live
    C = fm.adjoint(calib, inside, weight=m_full)
    support = (C >= MIN_COVERAGE).astype(np.float32)
    S = (d.scene if resp is None else resp.linearise(d.scene)).astype(np.float64) * support
    if first:
        mosaic = fm.adjoint(calib, target * inside, weight=m_full) / np.maximum(C, 1e-6)
        ix, iy = int(round(d.origin[0])), int(round(d.origin[1]))
        S = mosaic * support
        own = S[iy:iy + fm.h, ix:ix + fm.w]
        keep = support[iy:iy + fm.h, ix:ix + fm.w] > 0
        own[keep] = (d.scene if resp is None else resp.linearise(d.scene))[iy:iy + fm.h, ix:ix + fm.w][keep]
    d.coverage = C
    S = SceneOperator(d, model, support, live).solve(target, S, iters)
    if resp is not None:
        S = resp.counts(S)
    d.scene = (S * support).astype(np.float32)
    fpn_arr = None if fpn is None else np.asarray(fpn, np.float32)
    fm.set_reference(d.scene, fpn_arr, prescaled=True, origin=d.origin, support=support, subtract_fpn=False)


def _live_weight(d: RecData, live) -> np.ndarray:
    return (np.ones(len(d.measured), np.float32) if live is None
            else np.asarray(live, np.float32))[:, None, None]


class SceneOperator:
    """A: scene canvas → predicted motion frames of `d` under `model` (views, IIR, normalisation by the
    known-support weight, extra PSF), over the frames' valid pixels; its adjoint and a Jacobi
    preconditioner (the coverage). Linear in the canvas; leaves `d.fm`'s reference as it was."""

    def __init__(self, d: RecData, model: Model, support=None, live=None):
        self.d, self.calib, self.psf = d, model.calib, model.extra_psf_px
        fm = d.fm
        self._saved = (fm.reference, fm.fpn, fm.support, fm.origin)
        self.support = fm.support if support is None else support
        fm.set_reference(d.scene, None, prescaled=True, origin=d.origin, support=self.support)
        _, self.m = fm.predict_raw(self.calib)
        self.valid = (self.m >= 0.99).astype(np.float32) * _live_weight(d, live)
        self.dinv = np.where(self.support > 0, 1.0 / np.maximum(d.coverage, 1.0), 0.0)
        self._restore()

    def _restore(self):
        ref, fpn, support, origin = self._saved
        self.d.fm.set_reference(ref, fpn, prescaled=True, origin=origin, support=support, subtract_fpn=False)

    def apply(self, x) -> np.ndarray:
        """A x (the reference of `d.fm` left as it was)."""
        try:
            return self._forward(x)
        finally:
            self._restore()

    def _forward(self, x) -> np.ndarray:
        fm = self.d.fm
        fm.set_reference(np.asarray(x, np.float32), None, prescaled=True, origin=self.d.origin,
                         support=self.support)
        num, _ = fm.predict_raw(self.calib)
        out = np.where(self.m > 0.5, num / np.maximum(self.m, 0.5), 0.0).astype(np.float32)
        if self.psf > 0:
            g = fm._psf_kernel(self.psf)
            out = np.stack([cv2.sepFilter2D(o, -1, g, g, borderType=cv2.BORDER_REPLICATE) for o in out])
        return out * self.valid

    def adjoint(self, r) -> np.ndarray:
        return self.d.fm.adjoint(self.calib, r, self.psf, weight=self.m) * self.support

    def solve(self, target, x0, iters: int) -> np.ndarray:
        """x minimising Σ_valid (target − A x)² by Jacobi-preconditioned CGLS from `x0` (`iters` steps)."""
        try:
            S = np.asarray(x0, np.float64) * self.support
            r = ((target - self._forward(S)) if np.any(S) else target * self.valid).astype(np.float32)
            r *= self.valid
            s = self.adjoint(r)
            z = self.dinv * s
            pdir = z.copy()
            gamma = float(np.sum(s * z))
            for _ in range(iters):
                if gamma <= 0:
                    break
                q = self._forward(pdir)
                qq = float(np.sum(q.astype(np.float64) ** 2))
                if qq <= 0:
                    break
                a = gamma / qq
                S += a * pdir
                r -= (a * q).astype(np.float32)
                s = self.adjoint(r)
                z = self.dinv * s
                gamma_new = float(np.sum(s * z))
                pdir = z + (gamma_new / gamma) * pdir
                gamma = gamma_new
            return S
        finally:
            self._restore()


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
    warm: bool = False      # refits near a fitted value: local searches only
    project: bool = False   # motion only: local fits on the projected cost (`projection`), the canvas moving
    project_iters: int = 3  # their Levenberg–Marquardt steps
    fpn: bool = True        # the FPN is estimated (what `Problem.refresh` is told)

    @property
    def recs(self) -> list[RecData]:
        return self.problem.recs

    @classmethod
    def at(cls, problem: Problem, ev: Evaluation, named, model_tol: float, fpn: bool = True) -> StepContext:
        area = effective_area(ev.residuals)
        return cls(problem, chi2_scale=problem.noise_ss() / max(ev.n, 1) * area, n_eff=ev.n / area,
                   min_gain=(0.5 * model_tol) ** 2 * problem.signal_ss(), named=tuple(named), fpn=fpn)

    def delta_bic(self, ssr_before: float, ssr_after: float, n_params: int) -> float:
        """BIC gain on effective samples of a fit with `n_params` more parameters."""
        return self.n_eff * math.log(ssr_before / max(ssr_after, 1e-30)) - n_params * math.log(self.n_eff)


def mean_residual_map(ev: Evaluation, problem: Problem) -> np.ndarray:
    """RMS residual over the motion frames of the first recording (for the figures)."""
    d, r = problem.recs[0], ev.residuals[0]
    return np.sqrt(np.sum(r.astype(np.float64) ** 2, axis=0) / np.maximum(d.mask.sum(axis=0), 1))
