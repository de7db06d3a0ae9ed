"""The greedy search: which candidate effects the recordings support, in which order, and whether
structure is left that none of them explains (see the package docstring for the criteria)."""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from thermod.calib.discrepancy import identify
from thermod.calib.discrepancy.data import Model, RecData
from thermod.calib.discrepancy.diagnostics import diagnostics, pooled_response_signature, response_signature
from thermod.calib.discrepancy.effects import (
    CANDIDATES,
    EFFECTS,
    Effect,
    FitResult,
    format_params,
    format_resolution,
)
from thermod.calib.discrepancy.problem import Evaluation, Problem, StepContext, mean_residual_map
from thermod.errors import ConfigError, RecordingError
from thermod.io.json_safe import jsonable

log = logging.getLogger("thermod.calib.discrepancy")

GAP_DEFINITION = ("gap = ||measured - predicted|| / ||measured - reference view|| over pixels valid "
                  "in every view of the working-resolution motion frames (reference view: the static mean, "
                  "or for motion-only recordings the estimated scene seen from the pose at t_ref); "
                  "noise_floor = the gap of a perfect model given the temporal noise (see noise_source)")


@dataclass(frozen=True)
class Criteria:
    """When to search, what counts as significant, and when the rest is unexplained (see `analyse`)."""

    bic_min: float = 10.0
    min_explained: float = 0.3
    structured_excess: float = 0.3
    unexplained_excess: float = 1.0
    model_tol: float = 0.05
    signature_z: float = 6.0      # motion only: a response signature this significant (z score) …
    signature_gain: float = 0.04  # … and this large (gain change over ±3 RMS contrast) is structure left

    def allowance(self, problem: Problem, excess: float, tol: float) -> float:
        return problem.noise_ss() * (1.0 + excess) + tol**2 * problem.signal_ss()

    def worth_searching(self, problem: Problem, ssr: float) -> bool:
        return ssr > self.allowance(problem, self.structured_excess, 0.5 * self.model_tol)

    def unexplained(self, problem: Problem, ssr: float) -> bool:
        return ssr > self.allowance(problem, self.unexplained_excess, self.model_tol)


@dataclass
class Candidate:
    """One effect fitted in one step, with what it would buy."""

    effect: Effect
    fit: FitResult
    delta_bic: float
    explained: float        # fraction of the SSR's excess over the noise it removes
    seconds: float = 0.0
    state: list | None = None   # motion only: the scene (`Problem.state`) its projected fit was made on

    def significant(self, crit: Criteria, ctx: StepContext, ssr_before: float) -> bool:
        return (self.fit.n_params > 0 and self.delta_bic > crit.bic_min
                and self.explained >= crit.min_explained and ssr_before - self.fit.ssr >= ctx.min_gain)


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
    reference: str = "static"       # "static" (mean of a static lead-in) | "motion" (estimated scene)
    noise_source: str = "static frames"
    pruned: list = field(default_factory=list)     # effects named, then made redundant by later ones
    unexplained_reason: str = ""
    response_signature_z: float = 0.0
    response_signature_slope: float = 0.0
    response_signature_gain: float = 0.0    # the slope as a gain change over ±3 RMS contrast
    response_signature_pooled_z: float = 0.0
    identifiability: dict = field(default_factory=dict)   # `identify.Identifiability.report()`, if run
    ambiguous: list = field(default_factory=list)          # its ambiguous entries (none named)
    # motion only, when no timing effect was named or found ambiguous: what the recording resolves of
    # them at the final model (`identify.resolution_at`); a change within it cannot be named
    resolution: dict = field(default_factory=dict)
    capped: str = ""                # where the work cap stopped the search ("": it ran to the end)
    work: int = 0                   # forward-model pixel-steps the search computed
    max_work: float = 0.0

    @property
    def named(self) -> list[str]:
        return [s["effect"] for s in self.steps]

    @property
    def ambiguous_effects(self) -> list[str]:
        return [e for a in self.ambiguous for e in a["effects"]]

    def calibration(self):
        """The calibration to write: the final model's, with every ambiguous effect's parameters left at
        the values under test (an ambiguous value is one of several the data allow, not a measurement)."""
        if not self.ambiguous:
            return self.model.final_calibration()
        return identify.without(self.model, self.nominal, self.ambiguous_effects).final_calibration()

    def report(self) -> dict:
        return {
            "gap_initial": self.gap_initial, "gap_final": self.gap_final, "noise_floor": self.noise_floor,
            "steps": self.steps, "unexplained": self.unexplained,
            "model": self.calibration().as_dict(),
            "nominal": self.nominal.final_calibration().as_dict(),
            "unobservable": self.unobservable, "candidates": self.candidates_tried,
            "definition": GAP_DEFINITION, "seconds": self.seconds,
            "reference": self.reference, "noise_source": self.noise_source,
            "dropped": self.pruned, "unexplained_reason": self.unexplained_reason,
            "response_signature_z": self.response_signature_z,
            "response_signature_gain": self.response_signature_gain,
            "response_signature_pooled_z": self.response_signature_pooled_z,
            "ambiguous": self.ambiguous, "identifiability": self.identifiability,
            "resolution": self.resolution,
            "search_capped": self.capped, "work_pixel_steps": self.work,
            "max_work_pixel_steps": self.max_work,
        }

    def snapshot(self, label: str, problem: Problem, ev: Evaluation) -> None:
        gap = problem.gap(ev.ssr)
        self.snapshots.append((label, mean_residual_map(ev, problem), gap))
        self.gaps.append((label, gap, problem.noise_floor()))

    def record_candidate(self, c: Candidate, problem: Problem) -> None:
        self.candidates_tried.append({
            "step": len(self.steps) + 1, "effect": c.effect.name,
            "params": jsonable(c.effect.values(c.fit.model, self.nominal)), "gap": problem.gap(c.fit.ssr),
            "delta_bic": c.delta_bic, "excess_explained": c.explained, "unobservable": c.fit.unobservable})

    def record_step(self, c: Candidate, gap_before: float, gap_after: float, diag: dict) -> None:
        self.steps.append({
            "effect": c.effect.name, "params": {}, "gap_before": gap_before, "gap_after": gap_after,
            "delta_bic": c.delta_bic, "excess_explained": c.explained, "n_params": c.fit.n_params,
            "unobservable": c.fit.unobservable, "diagnostic": c.effect.diagnostic,
            "centroid_lag_median_s": diag["lag_median_s"]})
        if c.fit.unobservable:
            self.unobservable[c.effect.name] = c.fit.unobservable
        self.diags.append((c.effect.name, diag))

    def finish(self, model: Model, problem: Problem, ev: Evaluation, crit: Criteria, seconds: float) -> None:
        """Final model and verdict; every named effect reports its final value (refits may have moved it)."""
        self.model = model
        for st in self.steps:
            st["params"] = jsonable(EFFECTS[st["effect"]].values(model, self.nominal))
        self.gap_final = problem.gap(ev.ssr)
        self.noise_floor = problem.noise_floor()
        self.unexplained = bool(crit.unexplained(problem, ev.ssr))
        if self.unexplained:
            self.unexplained_reason = (f"the residual (gap {self.gap_final:.4f}) is well above the noise "
                                       f"floor ({self.noise_floor:.4f}) and the forward model's precision")
        contrast = _contrast(problem)
        slope, z = response_signature(problem, model, ev)
        gain = 6.0 * abs(slope) * contrast     # slope change of x = u + γu² over ±3 RMS contrast
        self.response_signature_z, self.response_signature_slope = z, slope
        self.response_signature_gain = gain
        pooled_slope, pooled_z = pooled_response_signature(problem, model, ev)
        self.response_signature_pooled_z = pooled_z

        def seen(sl: float, zz: float) -> bool:
            return abs(zz) > crit.signature_z and 6.0 * abs(sl) * contrast > crit.signature_gain
        if (problem.has_motion_reference and seen(slope, z) and seen(pooled_slope, pooled_z)
                and slope * pooled_slope > 0 and not self.unexplained):
            # Without a static reference the canvas takes a curved response in nearly whole: the gap
            # barely moves, but its one-sign trace where the blur mixes levels stays, and no gap
            # threshold sees it. A wrong motion's residual can follow the mixing variance too (both grow
            # with the blur), and the per-frame weighting that takes it out lets the forward model's own
            # small trace through on some flights: a curved response is the trace both measures see, with
            # one sign. The gain threshold keeps the forward model's trace on high-contrast scenes out.
            self.unexplained = True
            self.unexplained_reason = (
                f"the residual grows with the variance the blur mixes into each pixel (slope {slope:.3g} "
                f"per count, z = {z:.1f}, a {100 * gain:.1f} % gain change over the scene's contrast): a "
                "curved detector response the motion-only fit cannot take out (the estimated scene absorbs "
                "most of it); record a static lead-in to measure it")
        if self.steps:
            self.steps[-1]["gap_after"] = self.gap_final
        self.seconds = seconds


def _capped(problem: Problem, ana: Analysis, where: str, say) -> bool:
    """The work cap is reached (`Problem.exhausted`); the first time, the search's stop is recorded in
    `ana`, logged and said, naming the phase it stopped before."""
    if not problem.exhausted:
        return False
    if not ana.capped:
        ana.capped = (f"the search stopped early ({where}): the forward model's work reached its cap "
                      f"({problem.work / 1e9:.3g} of {problem.max_work / 1e9:.3g} G pixel-steps, "
                      f"{problem.n_evals} evaluations); what the search would have done next was not run")
        log.warning("%s: %s", ", ".join(d.name for d in problem.recs), ana.capped)
        say(ana.capped)
    return True


def _effects(candidates) -> list[Effect]:
    unknown = [c for c in candidates if c not in EFFECTS]
    if unknown:
        raise ConfigError(f"discrepancy: unknown candidate effect(s) {unknown}; known: {list(EFFECTS)}")
    return [EFFECTS[c] for c in candidates]


def _check_overlap(recs: list[RecData], min_pixels: int) -> None:
    for d in recs:
        if d.mask.sum() < min_pixels:
            raise RecordingError(d.name, "camera/frames", f"only {int(d.mask.sum())} pixels of the motion "
                                 f"frames stay inside the static reference view (need ≥ {min_pixels}); "
                                 "record a smaller motion or start it from the middle of the scene")


def _try(effect: Effect, ctx: StepContext, model: Model, ev: Evaluation) -> Candidate:
    t0 = time.monotonic()
    f = effect.fit(ctx, model)
    excess = max(ev.ssr - ctx.problem.noise_ss(), 1e-30)
    return Candidate(effect, f, ctx.delta_bic(ev.ssr, f.ssr, f.n_params), (ev.ssr - f.ssr) / excess,
                     time.monotonic() - t0)


def _refit(ctx: StepContext, model: Model, effects: list[Effect], fpn: bool, nominal: Model, say) -> Model:
    """Refit each effect once in turn with everything else in place, keeping what lowers the SSR;
    then, for an effect with flexible parameters (`Effect.collapse`), the same from the model with
    them folded, that effect last, kept when the SSR ends lower.

    Effects named early absorb part of the ones found later, and an FPN estimate made under an
    older model absorbs part of the newest effect: this one loop serves both. Flexible parameters
    (a gain per clipped run) can hold what a later effect (a bias) should explain, and a refit in
    turn does not leave that basin: the folded restart does.
    """
    problem = ctx.problem
    model = _refit_in_turn(ctx, model, effects, fpn, nominal, say)
    for effect in effects:
        start = effect.collapse(model) if effect.collapse is not None and len(effects) > 1 else None
        if start is None or problem.exhausted:
            continue
        problem.refresh(model, fpn=fpn)
        ssr = problem.evaluate(model).ssr
        problem.refresh(start, fpn=fpn)
        alt = _refit_in_turn(ctx, start, [e for e in effects if e is not effect] + [effect], fpn, nominal,
                             lambda msg: None)
        problem.refresh(alt, fpn=fpn)
        if problem.evaluate(alt).ssr < ssr:
            model = alt
            say(f"  refit from one {effect.name} parameter set: "
                + "; ".join(format_params(e.values(model, nominal)) for e in effects))
        else:
            problem.refresh(model, fpn=fpn)
    return model


def _refit_in_turn(ctx: StepContext, model: Model, effects: list[Effect], fpn: bool, nominal: Model,
                   say) -> Model:
    problem = ctx.problem
    for effect in effects:
        if problem.exhausted:       # `analyse` reports the cap at its next phase
            break
        f = effect.fit(ctx, model)
        if f.ssr < problem.evaluate(model).ssr:
            model = f.model
            problem.refresh(model, fpn=fpn)
            say(f"  refit {effect.name}: {format_params(effect.values(model, nominal))}")
    return model


def _settle(ctx: StepContext, model: Model, effects: list[Effect], nominal: Model, say,
            rounds: int = 6, min_drop: float = 0.02, min_share: float = 0.1) -> Model:
    """Motion only: refit `effects` in turn on the projected cost (`projection`: the canvas and FPN move
    with each step) until a round lowers the SSR by less than `min_drop` of it or by less than
    `min_share` of what a candidate must remove (`StepContext.min_gain`: a change the search itself
    would call insignificant). The canvas was estimated under a model that lacked the new effect and
    absorbed part of it (a 0.03 rad misalignment was first fitted at 0.022 rad; alternating canvas and
    model moved a roll-axis bias 0.0025 rad/s a round). On the real log from 9 s a 4 % scale error's
    rounds 3–6 moved the gap 0.0149 → 0.0138 (floor 0.0090), its factors not at all, for 50 s each."""
    problem = ctx.problem
    proj = dataclasses.replace(ctx, project=True, warm=True)
    before = problem.evaluate(model).ssr
    for _ in range(rounds):
        if problem.exhausted:       # `analyse` reports the cap at its next phase
            break
        problem.refresh(model, fpn=ctx.fpn, keep_mask=True)     # the canvas and FPN go on converging
        ssr = problem.evaluate(model).ssr
        problem.remember(model)
        for effect in effects:
            model, ssr = _adopt(problem, ctx.fpn, model, ssr, effect.fit(proj, model))
        say(f"  settled: gap {problem.gap(ssr):.4f}; "
            + "; ".join(f"{e.name} {format_params(e.values(model, nominal))}" for e in effects))
        drop, gain, before = 1.0 - ssr / before, before - ssr, ssr
        if drop < min_drop or gain < min_share * ctx.min_gain:
            break
    return model


def _adopt(problem: Problem, fpn: bool, model: Model, ssr: float, f: FitResult) -> tuple[Model, float]:
    """After a local fit on the projected cost: its model and SSR with the problem holding its canvas
    when it did better, else `model`'s. Fits without a projected mode (events, curves) were made on the
    canvas as it is: a better one is taken with a warm refresh of the canvas under it."""
    if f.ssr < ssr and problem.recall(f.model):
        return f.model, f.ssr
    if not problem.recall(model):
        problem.refresh(model, fpn=fpn, keep_mask=True)
    if f.ssr < ssr:
        problem.refresh(f.model, fpn=fpn, keep_mask=True)
        ssr_f = problem.evaluate(f.model).ssr
        if ssr_f < ssr:
            problem.remember(f.model)
            return f.model, ssr_f
        if not problem.recall(model):
            problem.refresh(model, fpn=fpn, keep_mask=True)
    return model, problem.evaluate(model).ssr


def _prune(ctx: StepContext, model: Model, crit: Criteria, ana: Analysis, say) -> Model:
    """Backward elimination after the refits: an effect whose parameters the later ones made redundant
    (put back to nominal and the others refitted locally, the SSR rises by less than a candidate must
    remove, or not decisively) is dropped from the model and the steps: a pure time offset named
    before the DLPF whose group delay it stood for, say (the default flight's case:
    benchmarks/results/discrepancy.md). The least needed goes first, one at a time."""
    problem = ctx.problem
    while len(ana.steps) > 1:
        ssr = problem.evaluate(model).ssr
        rise = {}
        for name in ana.named:
            reduced = EFFECTS[name].without(model, ana.nominal)
            best = (problem.evaluate(reduced).ssr, reduced)
            # the others refitted locally: they may take its share back, but not its fields (a readout
            # fit that keeps the mean row timing would move a time offset put back to nominal)
            warm = dataclasses.replace(ctx, warm=True, named=tuple(n for n in ana.named if n != name))
            for other in ana.named:
                if other != name:
                    f = EFFECTS[other].fit(warm, best[1])
                    best = min(best, (f.ssr, f.model), key=lambda b: b[0])
            rise[name] = best
        name = min(rise, key=lambda n: rise[n][0])
        ssr_without, reduced = rise[name]
        n_params = max(ana.steps[ana.named.index(name)]["n_params"], 1)
        if ssr_without - ssr >= ctx.min_gain and ctx.delta_bic(ssr_without, ssr, n_params) > crit.bic_min:
            break
        i = ana.named.index(name)
        ana.steps.pop(i)
        ana.diags.pop(i)
        ana.pruned.append({"effect": name, "params": jsonable(EFFECTS[name].values(model, ana.nominal)),
                           "gap_without": problem.gap(ssr_without), "gap_with": problem.gap(ssr)})
        ana.unobservable.pop(name, None)
        model = reduced
        say(f"  dropped {name}: the other effects make it redundant (gap {problem.gap(ssr):.4f} → "
            f"{problem.gap(ssr_without):.4f} without it)")
    return model


def analyse(recs: list[RecData], model: Model, *, candidates=CANDIDATES, max_steps: int = 4,
            bic_min: float = 10.0, min_explained: float = 0.3, structured_excess: float = 0.3,
            unexplained_excess: float = 1.0, model_tol: float = 0.05, fpn: bool = True,
            polish: bool = True, min_pixels: int = 2000, identifiability: bool = True,
            max_work: float = math.inf, progress=None) -> Analysis:
    """Greedy search for the missing effects (see the package docstring for the criteria).

    `structured_excess`: candidates are tried while SSR exceeds the noise expectation by this
    fraction (gap > √(1+x)·noise floor). `unexplained_excess`: what is left at the end counts as
    structured-but-unexplained above this larger fraction, which leaves room for the forward
    model's own approximation error. `model_tol`: the forward model's relative precision (gap units:
    resampling and interpolation at the working resolution, measured at 0.01–0.05 of the motion
    signal on simulator recordings; largest for sharp-edged scenes). Candidates are tried when
    ``SSR > noise·(1 + structured_excess) + (½ model_tol·‖signal‖)²`` and the rest is called
    unexplained when ``SSR > noise·(1 + unexplained_excess) + (model_tol·‖signal‖)²``; a candidate
    must also remove at least (model_tol·‖signal‖)² of SSR (practical significance: less is fitting
    resampling error). `min_explained`: a candidate must remove at least this fraction of the
    excess SSR. `bic_min`: decisive BIC gain on effective samples. `identifiability`: on motion-only
    recordings, the timing effects named are checked against their confounds (`identify`) before the
    verdict; those the motion cannot tell apart are reported `ambiguous`, not named. `max_work`: the
    forward-model work the search may do (`ForwardModel.work`); past it no further phase starts (a
    step under way names nothing) and `Analysis.capped` says where it stopped.
    """
    say = progress or (lambda msg: None)
    t_start = time.monotonic()
    remaining = _effects(candidates)
    crit = Criteria(bic_min, min_explained, structured_excess, unexplained_excess, model_tol)
    problem = Problem(recs, max_work=max_work)
    problem.refresh(model, fpn=fpn)
    _check_overlap(recs, min_pixels)
    ev = problem.evaluate(model, keep=True)
    ana = Analysis(problem.gap(ev.ssr), problem.gap(ev.ssr), problem.noise_floor(), [], False, model, model,
                   max_work=problem.max_work)
    kinds = sorted({d.reference for d in recs})
    ana.reference = kinds[0] if len(kinds) == 1 else "+".join(kinds)
    ana.noise_source = "; ".join(sorted({d.noise_source for d in recs}))
    say(f"gap {ana.gap_initial:.4f} (noise floor {ana.noise_floor:.4f}) over {ev.n} pixels of "
        f"{sum(len(d.frame_t) for d in recs)} motion frames at {recs[0].fm.w}×{recs[0].fm.h}")
    ana.snapshot("nominal", problem, ev)
    ctx = None
    searched = False
    while (remaining and len(ana.steps) < max_steps and crit.worth_searching(problem, ev.ssr)
           and not _capped(problem, ana, f"before step {len(ana.steps) + 1}", say)):
        searched = True
        ctx = StepContext.at(problem, ev, ana.named, model_tol, fpn)
        chosen = _search_step(ctx, model, ev, remaining, crit, ana, say)
        if chosen is None:
            break
        diag = diagnostics(problem, model, ev)
        gap_before = problem.gap(ev.ssr)
        implied = _implied(chosen, model, remaining, ana)
        model = chosen.fit.model
        if chosen.state is not None:      # motion only: the scene its projected fit moved with it
            problem.restore(chosen.state)
        problem.refresh(model, fpn=fpn, rebuild_scene=chosen.state is None)
        new = [chosen.effect] + implied
        ctx = dataclasses.replace(ctx, named=ctx.named + tuple(e.name for e in new))
        if problem.has_motion_reference:
            model = _settle(ctx, model, new + [EFFECTS[n] for n in ana.named], ana.nominal, say)
        else:
            again = (new if fpn else implied) + [EFFECTS[n] for n in ana.named]
            model = _refit(ctx, model, again, fpn, ana.nominal, say)
        _capped(problem, ana, f"in the refits after step {len(ana.steps) + 1}", say)   # the step stays named
        ev = problem.evaluate(model, keep=True)
        for e in new:
            fit = dataclasses.replace(chosen.fit, effect=e.name, n_params=1, unobservable=[])
            c = chosen if e is chosen.effect else dataclasses.replace(chosen, effect=e, fit=fit)
            ana.record_step(c, gap_before, problem.gap(ev.ssr), diag)
            say(f"→ {e.name}: {format_params(e.values(model, ana.nominal))}; "
                f"gap {gap_before:.4f} → {problem.gap(ev.ssr):.4f}"
                + (f" (moved by the {chosen.effect.name} fit)" if e is not chosen.effect else ""))
            remaining.remove(e)
        ana.snapshot("+".join(e.name for e in new), problem, ev)
    if polish and len(ana.steps) > 1 and not _capped(problem, ana, "before the final refits", say):
        model = _refit(ctx, model, [EFFECTS[n] for n in ana.named], fpn, ana.nominal, say)
        if not _capped(problem, ana, "before the backward elimination", say):
            model = _prune(ctx, model, crit, ana, say)
        ev = problem.evaluate(model, keep=True)
    # a residual worth a search, not beyond the model's precision, and no timing effect named: a pair
    # whose effects cancel one at a time (an offset of −readout/2) escapes the greedy search, not the
    # joint fit
    missed_timing = (searched and not set(ana.named) & set(identify.CONFOUNDED)
                     and not crit.unexplained(problem, ev.ssr))
    if (identifiability and problem.has_motion_reference
            and (set(ana.named) & identify.TRIGGERS or missed_timing)
            and not _capped(problem, ana, "before the identifiability check", say)):
        if missed_timing:
            say("the search named no timing effect over a residual worth one: the four fitted jointly")
        model = _identify(StepContext.at(problem, ev, ana.named, model_tol, fpn), model, crit, ana, say)
        ev = problem.evaluate(model, keep=True)
    if (problem.has_motion_reference and not set(ana.named) & set(identify.CONFOUNDED) and not ana.ambiguous
            and not _capped(problem, ana, "before the timing resolution", say)):
        say("what this recording resolves of the timing effects (smaller changes cannot be named):")
        ana.resolution = identify.resolution_at(StepContext.at(problem, ev, ana.named, model_tol, fpn),
                                                model, ana.nominal)
        say("  " + format_resolution(ana.resolution))
        ev = problem.evaluate(model, keep=True)
    ana.work = problem.work
    ana.finish(model, problem, ev, crit, time.monotonic() - t_start)
    for a in ana.ambiguous:
        say(f"{a['label']} — " + "; ".join(a["evidence"])
            + f"; to separate them record {a['separating_motion']}")
    left = ("the search stopped early, before a candidate explained it" if ana.capped
            else "no candidate explains it")
    say(f"final gap {ana.gap_final:.4f} (noise floor {ana.noise_floor:.4f}); "
        + (f"remaining residual is structured but {left}: UNEXPLAINED "
           f"({ana.unexplained_reason})" if ana.unexplained else "residual at the noise level"))
    return ana


def _identify(ctx: StepContext, model: Model, crit: Criteria, ana: Analysis, say) -> Model:
    """`identify.check` on the search's model; the steps then hold what it identified: a timing effect
    the search named that fails is moved to `ambiguous` or dropped, one it identified that the search
    had not named is added (with the diagnostics of the model without it)."""
    say("identifiability of the timing effects (joint fit, curvature, each held at nominal):")
    final, ident = identify.check(ctx, model, ana.nominal, ana.named, crit.bic_min, say)
    problem = ctx.problem
    for name in [n for n in ana.named if n in identify.CONFOUNDED and n not in ident.identified]:
        i = ana.named.index(name)
        ana.steps.pop(i)
        ana.diags.pop(i)
        ana.unobservable.pop(name, None)
        if name in ident.dropped:
            t = ident.tests.get(name, {})
            ana.pruned.append({"effect": name, "params": jsonable(EFFECTS[name].values(model, ana.nominal)),
                               "gap_without": t.get("gap_without", float("nan")),
                               "gap_with": t.get("gap_joint", float("nan"))})
    for name in [n for n in ident.identified if n not in ana.named]:
        t = ident.tests[name]
        reduced = identify.without(final, ana.nominal, [name])
        ev = problem.evaluate(reduced, keep=True)
        ana.steps.append({
            "effect": name, "params": {}, "gap_before": t["gap_without"], "gap_after": t["gap_joint"],
            "delta_bic": t["delta_bic"], "excess_explained": float("nan"),
            "n_params": identify.n_params(name), "unobservable": [],
            "diagnostic": EFFECTS[name].diagnostic, "centroid_lag_median_s": float("nan"),
            "named_by": "joint fit"})
        ana.diags.append((name, diagnostics(problem, reduced, ev)))
        say(f"→ {name}: identified by the joint fit "
            f"({format_params(EFFECTS[name].values(final, ana.nominal))})")
    ana.ambiguous = ident.ambiguous
    ana.identifiability = jsonable(ident.report())
    ana.snapshot("joint timing fit", problem, problem.evaluate(final, keep=True))
    return final


def _contrast(problem: Problem) -> float:
    """RMS contrast (counts) of the references over the pixels the fit uses."""
    vals = [d.static_mean[d.mask.any(axis=0)] - (d.fpn[d.mask.any(axis=0)] if d.fpn is not None else 0.0)
            for d in problem.recs]
    return float(np.concatenate(vals).std()) if vals else 0.0


def _implied(chosen: Candidate, model: Model, remaining: list[Effect], ana: Analysis) -> list[Effect]:
    """The effects the chosen fit moved besides its own (`Effect.implies`: a readout fitted with the mean
    row timing kept moves the time offset, and does so only where the data demand it): named with it."""
    out = []
    for name in chosen.effect.implies:
        e = EFFECTS.get(name)
        if e is None or e not in remaining or name in ana.named:
            continue
        if e.values(chosen.fit.model, ana.nominal) != e.values(model, ana.nominal):
            out.append(e)
    return out


def _search_step(ctx: StepContext, model: Model, ev: Evaluation, remaining: list[Effect], crit: Criteria,
                 ana: Analysis, say) -> Candidate | None:
    """Fit every remaining candidate; the significant one explaining most of the excess, or None."""
    tried = []
    for effect in remaining:
        if _capped(ctx.problem, ana, f"in step {len(ana.steps) + 1}, before the {effect.name} fit", say):
            return None             # a step not all candidates were tried in names none of them
        c = _try(effect, ctx, model, ev)
        ana.record_candidate(c, ctx.problem)
        say(f"  {effect.name:16s} gap {ctx.problem.gap(c.fit.ssr):.4f}  "
            f"explains {100 * c.explained:5.1f} % of the excess  ΔBIC {c.delta_bic:9.1f}  "
            f"{format_params(effect.values(c.fit.model, ana.nominal))}  ({c.seconds:.1f} s)")
        tried.append(c)
    ssr_before = ev.ssr
    if ctx.problem.has_motion_reference:
        tried, ssr_before = _project_scene(ctx, model, ev, tried, ana, say)
        if ana.capped:
            return None
    ok = [c for c in tried if c.significant(crit, ctx, ssr_before)]
    for c in [c for c in ok if not _beats_simpler(c, tried, ctx, crit)]:
        say(f"  {c.effect.name}: not decisively better than {c.effect.simpler}, which it generalises")
        ok.remove(c)
    if not ok:
        say("  no candidate is significant")
        return None
    return max(ok, key=lambda c: c.explained)


def _beats_simpler(c: Candidate, tried: list[Candidate], ctx: StepContext, crit: Criteria) -> bool:
    """A candidate that generalises another (`Effect.simpler`: clock drift and the gyro low-pass a time
    offset) must beat that one's fit, made on the same footing (fixed canvas, or both projected),
    decisively: ΔBIC > `bic_min` for its extra parameters, and it removes `min_explained` of what the
    simpler one leaves above the noise and at least what any candidate must (`min_gain`: where the
    simpler one is at the floor already, a share of nothing is no test; a 6 ms offset beside a gyro
    bias was named a 595 ppm clock drift so). Otherwise the simpler one is what the data show."""
    s = next((t for t in tried if t.effect.name == c.effect.simpler), None)
    if s is None or s.fit.n_params == 0 or (s.state is None) != (c.state is None):
        return True
    excess = max(s.fit.ssr - ctx.problem.noise_ss(), 0.0)
    extra = max(c.fit.n_params - s.fit.n_params, 0)
    gain = s.fit.ssr - c.fit.ssr
    return (ctx.delta_bic(s.fit.ssr, c.fit.ssr, extra) > crit.bic_min
            and gain >= max(crit.min_explained * excess, ctx.min_gain))


def _project_scene(ctx: StepContext, model: Model, ev: Evaluation, tried: list[Candidate], ana: Analysis, say,
                   top: int = 3, share: float = 0.25, scene_iters: int = 3, steps: int = 2
                   ) -> tuple[list[Candidate], float]:
    """Motion only: rank the best few candidates on the projected cost, the SSR minimised over the scene
    too. The step's scene canvas was estimated under the current, wrong model, so it has absorbed part
    of the missing effect: on it a candidate's fit falls short of the effect (a 4–5 % scale error on a
    pitch-and-roll flight was fitted at 0.3 %), and one that merely mimics what is left can beat the
    right one.

    Each of the `top` candidates by explained excess (those explaining at least `share` of what the
    best one does) gets a canvas rebuilt under its step-canvas fit (`Problem.refresh` with
    `rebuild_scene`: the mosaic, then `scene_iters` CGLS iterations, the FPN with it) and is refitted
    from there on the projected cost (`projection.projected_lm`, `steps` steps: enough to rank them; the
    chosen one goes on in `_settle`). The baseline is the current model's
    cost on a canvas rebuilt and refined alike. Returns the candidates with their projected fits,
    statistics and scene state (the search goes on from the chosen one's), and the baseline SSR."""
    problem = ctx.problem
    fitted = sorted((c for c in tried if c.fit.n_params > 0 and c.explained > 0), key=lambda c: -c.explained)
    best = [c for c in fitted[:top] if c.explained >= share * fitted[0].explained] if fitted else []
    # the effects these generalise are projected too: a nested one is judged against them (`_beats_simpler`)
    names = {c.effect.name for c in best}
    best += [c for c in fitted if c.effect.name not in names
             and any(b.effect.simpler == c.effect.name for b in best)]
    if not best:
        return tried, ev.ssr
    proj = dataclasses.replace(ctx, project=True, warm=True, project_iters=steps)
    saved, iters = problem.state(), problem.scene_iters
    problem.scene_iters = scene_iters

    def rebuilt(m: Model) -> float:
        problem.restore(saved)
        problem.refresh(m, fpn=ctx.fpn, keep_mask=True, rebuild_scene=True)
        return problem.evaluate(m).ssr

    try:
        rebuilt(model)
        for _ in range(steps):      # as much canvas refinement as a projected fit's accepted steps
            problem.refresh(model, fpn=ctx.fpn, keep_mask=True)
        base = problem.evaluate(model).ssr
        base_gap = problem.gap(base)
        out = []
        excess = max(base - problem.noise_ss(), 1e-30)
        for c in best:
            if _capped(problem, ana, f"in step {len(ana.steps) + 1}, before the projected {c.effect.name} "
                       "fit", say):
                break
            t0 = time.monotonic()
            m_best, ssr_best = c.fit.model, rebuilt(c.fit.model)
            problem.remember(m_best)
            m_best, ssr_best = _adopt(problem, ctx.fpn, m_best, ssr_best, c.effect.fit(proj, m_best))
            state = problem.state()
            f = dataclasses.replace(c.fit, model=m_best, ssr=ssr_best)
            p = Candidate(c.effect, f, ctx.delta_bic(base, f.ssr, f.n_params), (base - f.ssr) / excess,
                          c.seconds + time.monotonic() - t0, state)
            say(f"  projected {c.effect.name:16s} gap {problem.gap(f.ssr):.4f} (baseline "
                f"{base_gap:.4f})  explains {100 * p.explained:5.1f} %  ΔBIC {p.delta_bic:9.1f}  "
                f"{format_params(c.effect.values(f.model, ana.nominal))}  ({time.monotonic() - t0:.1f} s)")
            out.append(p)
    finally:
        problem.restore(saved)
        problem.scene_iters = iters
    return out, base
