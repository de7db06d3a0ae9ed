"""Identifiability of the timing effects before they are named (motion-only recordings).

Offset, readout, bias and τ move the frames through the same rates (a readout's mean delay is an
offset, a bias stands in for both over a short stretch, τ acts as a delay for slow motion), and the
greedy search names them one at a time. `check` fits the four jointly on the projected cost
(`projection.projected_lm`), takes each parameter's σ, resolution and the pairs' correlations from
the projected Jacobian, and holds each effect at nominal with the others refitted: an effect is named
only when the SSR then rises decisively (ΔBIC > `bic_min`, a rise ≥ `min_gain`) and the curvature
puts its value that far from nominal too. Effects that fail but are needed as a set form an
`ambiguous` entry (with their correlated confounds, |ρ| ≥ `AMBIGUOUS_CORRELATION`), with the evidence
and the motion that would separate them; none of them is named or written as known. The rule in
full: docs/design.md §8, "Identifiability before naming".
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from thermod.calib.discrepancy.data import Model
from thermod.calib.discrepancy.fitting import with_calib
from thermod.calib.discrepancy.problem import StepContext, effective_area
from thermod.calib.discrepancy.projection import projected_jacobian, projected_lm

CONFOUNDED = ("time_offset", "rolling_readout", "gyro_bias", "time_constant")
#: The named effects that start the check: a readout, offset or bias; τ named alone is a delay of its own
#: shape (an exponential, not a shift), which the search already tells from an offset (`simpler`).
TRIGGERS = frozenset(("time_offset", "rolling_readout", "gyro_bias"))
# an effect that failed the test and a confound correlated at least this much are reported together
AMBIGUOUS_CORRELATION = 0.8
# an effect that failed the test but whose absence alone costs this share of min_gain carries part of the
# structure the set explains (two weak effects that substitute for each other)
CARRIES_SHARE = 0.25

# parameter layout: (effect, label, unit); units are the step scale of the fits (h = ½ unit moves the
# image by a fraction of a pixel at flight rates)
_MS = 2e-3
_BIAS = math.radians(0.2)
PARAMS = (("time_offset", "time_offset_s", _MS), ("rolling_readout", "readout_s", _MS),
          ("gyro_bias", "bias_x_rad_s", _BIAS), ("gyro_bias", "bias_y_rad_s", _BIAS),
          ("gyro_bias", "bias_z_rad_s", _BIAS), ("time_constant", "tau_s", _MS))
UNITS = np.array([p[2] for p in PARAMS])

# what motion separates each pair (the physics of the two effects' signatures)
SEPARATING_MOTION = {
    frozenset({"rolling_readout", "time_offset"}):
        "a roll or pitch rate that varies within a frame period (rows read at different times then see "
        "different rotations, a delay of the whole frame does not), over a longer flight",
    frozenset({"gyro_bias", "time_offset"}):
        "rates that change sign and size over the flight (a bias is a constant rate, an offset scales "
        "with the rate), or a static lead-in that measures the bias",
    frozenset({"gyro_bias", "rolling_readout"}):
        "rates that change sign and size over the flight, with roll or pitch varying within a frame period",
    frozenset({"time_constant", "time_offset"}):
        "motion that starts and stops (τ smears along the angular acceleration, an offset shifts along "
        "the rate)",
    frozenset({"time_constant", "rolling_readout"}):
        "motion that starts and stops, with roll or pitch varying within a frame period",
    frozenset({"time_constant", "gyro_bias"}):
        "motion that starts and stops, with rates that change sign over the flight",
}


@dataclass
class Identifiability:
    """What the joint fit says (see the module docstring); `report()` is its JSON form."""

    params: list                        # labels of the fitted parameters
    values: list                        # the fit kept (identified and ambiguous at the joint fit)
    nominal: list
    sigma: list                         # 1σ from the noise (statistical), physical units
    resolution: list                    # the same with min_gain as the unit: what the model can resolve
    correlation: list                   # ρ matrix
    gap_joint: float
    tests: dict                         # effect → profile test
    identified: list
    ambiguous: list = field(default_factory=list)
    dropped: list = field(default_factory=list)       # failed, and not needed as a set either
    unresolved: list = field(default_factory=list)    # axes of an identified effect held at nominal
    rule: str = ""

    def report(self) -> dict:
        return dataclasses.asdict(self)


def _x_of(model: Model, nominal: Model) -> np.ndarray:
    c, c0 = model.calib, nominal.calib
    v = np.array([c.time_offset_s, c.readout_s, *c.bias_rad_s, c.tau_s], float)
    v0 = np.array([c0.time_offset_s, c0.readout_s, *c0.bias_rad_s, c0.tau_s], float)
    return (v - v0) / UNITS


def _make(model: Model, nominal: Model, x: np.ndarray) -> Model:
    c0 = nominal.calib
    v = np.array([c0.time_offset_s, c0.readout_s, *c0.bias_rad_s, c0.tau_s], float) + np.asarray(x) * UNITS
    return with_calib(model, time_offset_s=float(v[0]), readout_s=float(v[1]),
                      bias_rad_s=tuple(float(b) for b in v[2:5]), tau_s=float(v[5]))


def _bounds(nominal: Model) -> tuple[np.ndarray, np.ndarray]:
    c0 = nominal.calib
    b = math.radians(20.0)
    lo = np.array([-0.03, -c0.readout_s, -b, -b, -b, c0.tau_s / 3 - c0.tau_s]) / UNITS
    hi = np.array([0.03, 1.0 / c0.frame_rate_hz - c0.readout_s, b, b, b, 3 * c0.tau_s - c0.tau_s]) / UNITS
    return lo, hi


def without(model: Model, nominal: Model, effects) -> Model:
    """`model` with the parameters of `effects` (of the four) at `nominal`'s values, the rest as they are."""
    x = _x_of(model, nominal)
    x[_index(set(effects))] = 0.0
    return _make(model, nominal, x)


def n_params(effect: str) -> int:
    return sum(p[0] == effect for p in PARAMS)


def _index(effects) -> np.ndarray:
    return np.array([i for i, p in enumerate(PARAMS) if p[0] in effects], int)


class _Fitter:
    """Fits of the four effects' parameters with some held at nominal, each from the search's canvas
    and each judged on a canvas rebuilt and refined alike (so their SSRs compare)."""

    def __init__(self, ctx: StepContext, model: Model, nominal: Model, iters: int):
        self.ctx, self.model, self.nominal, self.iters = ctx, model, nominal, iters
        self.problem = ctx.problem
        self.saved = self.problem.state()
        self.lo, self.hi = _bounds(nominal)

    def fit(self, x0: np.ndarray, free: np.ndarray) -> np.ndarray:
        x0 = np.clip(np.asarray(x0, float), self.lo, self.hi)
        if len(free) == 0:
            return x0

        def make(u):
            x = x0.copy()
            x[free] = u
            return _make(self.model, self.nominal, x)
        self.problem.restore(self.saved)
        self.problem.refresh(make(x0[free]), fpn=self.ctx.fpn, keep_mask=True)
        u, _ = projected_lm(self.ctx, make, x0[free], self.lo[free], self.hi[free], h=0.5, iters=self.iters)
        x = x0.copy()
        x[free] = u
        return x

    def ssr(self, x: np.ndarray) -> float:
        m = _make(self.model, self.nominal, x)
        self.problem.restore(self.saved)
        self.problem.refresh(m, fpn=self.ctx.fpn, keep_mask=True, rebuild_scene=True)
        self.problem.refresh(m, fpn=self.ctx.fpn, keep_mask=True)
        return self.problem.evaluate(m).ssr

    def start_without(self, x: np.ndarray, held: set) -> np.ndarray:
        """Where a profile starts: `x` with `held` at nominal, and the mean delay they carried moved to a
        free delay parameter (a readout's T_ro/2 and τ's shift to the offset, an offset's to 2× readout)
        when that evaluates lower."""
        plain = x.copy()
        plain[_index(held)] = 0.0
        moved = plain.copy()
        delay = ((x[0] if "time_offset" in held else 0.0) + (x[5] if "time_constant" in held else 0.0)
                 + (0.5 * x[1] if "rolling_readout" in held else 0.0))
        if "time_offset" not in held:
            moved[0] += delay
        elif "rolling_readout" not in held:
            moved[1] += 2.0 * delay
        moved = np.clip(moved, self.lo, self.hi)
        if np.allclose(moved, plain):
            return plain
        return min((plain, moved), key=self.ssr)


def _decisive(ctx: StepContext, ssr_without: float, ssr_with: float, k: int, bic_min: float) -> tuple:
    dbic = ctx.delta_bic(ssr_without, ssr_with, k)
    return bool(dbic > bic_min and ssr_without - ssr_with >= ctx.min_gain), dbic


def check(ctx: StepContext, model: Model, nominal: Model, named: list[str], bic_min: float, say,
          iters: int = 5) -> tuple[Model, Identifiability]:
    """The rule of the module docstring for the search's model (`named`: the effects it named). Returns the
    model to keep (joint-fit values for identified and ambiguous effects, nominal for dropped ones) and
    the evidence; the problem is left holding that model's canvas."""
    problem = ctx.problem
    fitter = _Fitter(ctx, model, nominal, iters)
    # an effect outside the set that owns the offset (a clock drift, a low-pass) keeps it free throughout
    offset_owned = any(n not in CONFOUNDED and n in ("clock_drift", "gyro_lowpass") for n in named)
    tested = [e for e in CONFOUNDED if not (e == "time_offset" and offset_owned)]
    every = np.arange(len(PARAMS))
    x0 = _x_of(model, nominal)
    # the joint fit starts from the search's model, or from it with the offset's delay handed to the
    # readout (T_ro = 2·offset: the same mean row delay), whichever fits better: the readout the search
    # took for an offset lies along a valley the fit would otherwise crawl
    swapped = x0.copy()
    swapped[1], swapped[0] = x0[1] + 2.0 * x0[0], 0.0
    swapped = np.clip(swapped, fitter.lo, fitter.hi)
    if swapped[1] != x0[1]:
        x0 = min((x0, swapped), key=fitter.ssr)
    x_joint = fitter.fit(x0, every)
    ssr_joint = fitter.ssr(x_joint)
    say(f"  joint fit of {', '.join(CONFOUNDED)}: gap {problem.gap(ssr_joint):.4f}")

    _, info_inv, sd_u, res_u, rho = _curvature(ctx, model, nominal, x_joint)

    c0 = nominal.calib
    nom = np.array([c0.time_offset_s, c0.readout_s, *c0.bias_rad_s, c0.tau_s], float)
    profiles = {}
    for e in tested:
        idx = _index({e})
        x = fitter.fit(fitter.start_without(x_joint, {e}), np.setdiff1d(every, idx))
        profiles[e] = (x, fitter.ssr(x))
    # a profile can end lower than the joint fit (a valley the joint fit did not leave): the best is the joint
    best = min(profiles, key=lambda e: profiles[e][1], default=None)
    if best is not None and profiles[best][1] < ssr_joint:
        x_joint, ssr_joint = profiles[best]
        say(f"  joint fit taken from the profile without {best}: gap {problem.gap(ssr_joint):.4f}")
    tests, ok = {}, []
    for e, (x, ssr) in profiles.items():
        idx = _index({e})
        passed, dbic = _decisive(ctx, ssr, ssr_joint, len(idx), bic_min)
        # the curvature's account of the same rise: the joint value's distance from nominal in the metric
        # of its marginal covariance (a profile that stopped short of its minimum overstates the rise)
        xe = x_joint[idx]
        rise_lin = float(xe @ np.linalg.pinv(info_inv[np.ix_(idx, idx)]) @ xe)
        passed = passed and rise_lin >= ctx.min_gain
        tests[e] = {"gap_without": problem.gap(ssr), "gap_joint": problem.gap(ssr_joint),
                    "delta_ssr_share": (ssr - ssr_joint) / max(ctx.min_gain, 1e-30), "delta_bic": dbic,
                    "curvature_rise_share": rise_lin / max(ctx.min_gain, 1e-30), "identified": passed,
                    "others_without": {PARAMS[i][1]: float(nom[i] + x[i] * UNITS[i])
                                       for i in range(len(PARAMS)) if i not in idx}}
        say(f"  without {e} (the others refitted): gap {problem.gap(ssr):.4f} (joint "
            f"{problem.gap(ssr_joint):.4f}), ΔBIC {dbic:.1f}, rise {tests[e]['delta_ssr_share']:.2f} × "
            f"min_gain (curvature: {rise_lin / max(ctx.min_gain, 1e-30):.2f}): "
            f"{'identified' if passed else 'not identified'}")
        if passed:
            ok.append(e)
    rest = [e for e in tested if e not in ok]
    x_final = x_joint
    ambiguous, dropped = [], []
    if rest:
        held = set(rest)
        x_rest = fitter.fit(fitter.start_without(x_joint, held), np.setdiff1d(every, _index(held)))
        ssr_rest = fitter.ssr(x_rest)
        needed, dbic_rest = _decisive(ctx, ssr_rest, ssr_joint, len(_index(held)), bic_min)
        if needed:
            ambiguous = _ambiguous_entries(rest, named, rho, sd_u, res_u, x_joint, nom, tests,
                                           problem.gap(ssr_rest), problem.gap(ssr_joint), dbic_rest)
            dropped = [e for e in rest if not any(e in a["effects"] for a in ambiguous)]
            if dropped:
                x_final = x_joint.copy()
                x_final[_index(set(dropped))] = 0.0
                x_final = fitter.fit(x_final, np.setdiff1d(every, _index(set(dropped))))
        else:
            dropped, x_final = rest, x_rest
    x_final, unresolved = _hold_unresolved_axes(fitter, ok, x_final, res_u, sd_u, nom, dropped)
    for u in unresolved:
        say(f"  {u['effect']} {u['param']}: {u['joint_value']:.4g} is within its resolution "
            f"±{u['resolution']:.2g} of nominal: held at nominal, not named")
    vals = x_final * UNITS
    ident = Identifiability(
        params=[p[1] for p in PARAMS], values=[float(v + n) for v, n in zip(vals, nom, strict=True)],
        nominal=[float(v) for v in nom], sigma=[float(s) for s in sd_u * UNITS],
        resolution=[float(s) for s in res_u * UNITS],
        correlation=[[round(float(v), 4) for v in row] for row in rho], gap_joint=problem.gap(ssr_joint),
        tests=tests, identified=ok, ambiguous=ambiguous, dropped=dropped, unresolved=unresolved,
        rule=RULE.format(bic_min=bic_min))
    final = _make(model, nominal, x_final)
    problem.restore(fitter.saved)
    if np.array_equal(x_final, _x_of(model, nominal)):
        return model, ident              # nothing moved: the search's own canvas stands
    problem.refresh(final, fpn=ctx.fpn, keep_mask=True, rebuild_scene=True)
    problem.refresh(final, fpn=ctx.fpn, keep_mask=True)
    return final, ident


def _curvature(ctx: StepContext, model: Model, nominal: Model, x: np.ndarray) -> tuple:
    """(JᵀJ, (JᵀJ)⁺, σ, resolution, ρ) of the parameters at `x` (units of `UNITS`), from the projected
    Jacobian (what the canvas can take is no information). σ: one independent sample's variance (the
    residual's, or the noise's if lower, per pixel, times the pixels per independent sample) through the
    inverse curvature; resolution: the move that, the others refitted, raises the SSR by min_gain."""
    problem = ctx.problem
    ev = problem.evaluate(_make(model, nominal, x), keep=True)
    lo, hi = _bounds(nominal)
    J, _, _ = projected_jacobian(problem, lambda v: _make(model, nominal, v), x, ev, 0.5, lo, hi,
                                 problem.scene_iters)
    s2 = max(ev.ssr, problem.noise_ss()) / max(ev.n, 1) * effective_area(ev.residuals)
    info = J.T @ J
    info_inv = np.linalg.pinv(info)
    cov_u = s2 * info_inv
    sd_u = np.sqrt(np.maximum(np.diag(cov_u), 0.0))
    res_u = np.sqrt(np.maximum(np.diag(info_inv), 0.0) * ctx.min_gain)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.nan_to_num(cov_u / np.outer(sd_u, sd_u))
    np.fill_diagonal(rho, 1.0)
    return info, info_inv, sd_u, res_u, rho


def resolution_at(ctx: StepContext, model: Model, nominal: Model) -> dict:
    """What the recording resolves at `model`, in physical units: ``parameters`` holds, per parameter of
    the four effects, its resolution (the smallest change from the model that the naming rule could
    name: the SSR rises by min_gain, the others refitted) and 1σ; ``rise`` [6, 6] is the curvature in
    units of min_gain, so a change Δ of all six raises the SSR by about Δᵀ·rise·Δ·min_gain. A change
    whose rise is below 1 is below what this motion can tell, whatever fit is tried."""
    x = _x_of(model, nominal)
    info, _, sd_u, res_u, _ = _curvature(ctx, model, nominal, x)
    rise = info / max(ctx.min_gain, 1e-30) / np.outer(UNITS, UNITS)
    return {"parameters": {p[1]: {"effect": p[0], "resolution": float(r * p[2]), "sigma": float(sd * p[2])}
                           for p, r, sd in zip(PARAMS, res_u, sd_u, strict=True)},
            "rise": [[float(v) for v in row] for row in rise]}


def _hold_unresolved_axes(fitter: _Fitter, identified, x, res_u, sd_u, nom, dropped) -> tuple:
    """An identified effect of several parameters (the bias's three axes) is named axis by axis: an axis
    whose joint value lies within its resolution of nominal (held there alone, the SSR would rise by
    less than min_gain: the rule for an effect, per axis) is held at nominal and the rest refitted,
    unless every axis is (the effect is then resolved only as a whole, and kept). Returns the values
    and one entry per held axis."""
    held = []
    for e in identified:
        idx = _index({e})
        weak = [int(i) for i in idx if abs(x[i]) < res_u[i]]
        if len(idx) > 1 and 0 < len(weak) < len(idx):
            held += [(e, i) for i in weak]
    if not held:
        return x, []
    out = [{"effect": e, "param": PARAMS[i][1], "joint_value": float(nom[i] + x[i] * UNITS[i]),
            "resolution": float(res_u[i] * UNITS[i]), "sigma": float(sd_u[i] * UNITS[i])} for e, i in held]
    x = x.copy()
    fixed = [i for _, i in held] + list(_index(set(dropped)))
    x[fixed] = 0.0
    return fitter.fit(x, np.setdiff1d(np.arange(len(PARAMS)), fixed)), out


RULE = ("an effect among time_offset, rolling_readout, gyro_bias, time_constant is named only when, held "
        "at nominal with the other three refitted jointly (projected cost), the SSR rises decisively: "
        "ΔBIC > {bic_min:g} on effective samples for its parameters and by at least min_gain (the forward "
        "model's precision, (½·model_tol)² of the signal), and the joint fit's curvature puts its value "
        "that far from nominal too; effects that fail but are needed as a set "
        "(the same test for the set) are reported ambiguous, not named; an axis of a named bias within "
        "its resolution of nominal is held there (not resolved by this motion)")


def effect_correlation(rho: np.ndarray, a: str, b: str) -> float:
    """The largest |ρ| between a parameter of effect `a` and one of `b`, with its sign."""
    best = 0.0
    for i in _index({a}):
        for j in _index({b}):
            if abs(rho[i, j]) > abs(best):
                best = float(rho[i, j])
    return best


def _stand_ins(e: str, tests: dict, x_joint, nom, res_u) -> list[str]:
    """The effects whose parameters moved by at least half their resolution when `e` was held at nominal
    (the profile), largest move first; at least the one that moved most."""
    moved = {}
    for o in CONFOUNDED:
        if o == e or e not in tests:
            continue
        profile = tests[e]["others_without"]
        steps = [abs(profile[PARAMS[i][1]] - nom[i] - x_joint[i] * UNITS[i]) / max(res_u[i] * UNITS[i], 1e-30)
                 for i in _index({o}) if PARAMS[i][1] in profile]
        if steps:
            moved[o] = max(steps)
    ranked = sorted(moved, key=lambda o: -moved[o])
    return [o for o in ranked if moved[o] >= 0.5] or ranked[:1]


def _ambiguous_entries(rest, named, rho, sd_u, res_u, x_joint, nom, tests, gap_without, gap_joint,
                       dbic) -> list:
    """One entry for the effects that failed the test but are needed as a set: those the search named and
    those whose absence alone costs a share (≥ `CARRIES_SHARE` of min_gain: they carry part of it), then
    their confounds correlated at ≥ AMBIGUOUS_CORRELATION; the ones whose absence costs most lead."""
    core = [e for e in rest if e in named or tests[e]["delta_ssr_share"] >= CARRIES_SHARE] or list(rest)
    group = list(core)
    for e in rest:
        if e not in group and any(abs(effect_correlation(rho, e, c)) >= AMBIGUOUS_CORRELATION for c in core):
            group.append(e)
    if len(group) == 1:       # alone it failed: its confounds are what moved to stand in for it
        group += _stand_ins(group[0], tests, x_joint, nom, res_u)
    group.sort(key=lambda e: -tests[e]["delta_ssr_share"] if e in tests else 0.0)
    lead = group[:2] if len(group) >= 2 else group
    label = " | ".join(lead) + (f" (+ {', '.join(group[2:])})" if len(group) > 2 else "")
    pairs = {f"{a}|{b}": effect_correlation(rho, a, b) for i, a in enumerate(group) for b in group[i + 1:]}
    sig = {PARAMS[i][1]: float(sd_u[i] * UNITS[i]) for i in _index(set(group))}
    res = {PARAMS[i][1]: float(res_u[i] * UNITS[i]) for i in _index(set(group))}
    motions = [SEPARATING_MOTION[frozenset({a, b})] for i, a in enumerate(group) for b in group[i + 1:]
               if frozenset({a, b}) in SEPARATING_MOTION]
    evidence = [f"held at nominal together, the SSR rises decisively (gap {gap_joint:.4f} → "
                f"{gap_without:.4f}, ΔBIC {dbic:.0f}): the structure is real"]
    evidence += [f"without {e} alone (the others refitted): gap {tests[e]['gap_without']:.4f}, a rise of "
                 f"{tests[e]['delta_ssr_share']:.2f} × min_gain (ΔBIC {tests[e]['delta_bic']:.0f}; naming "
                 "needs ≥ 1 and ΔBIC > bic_min): the others stand in for it" for e in group if e in tests]
    evidence += [f"correlation {k}: {v:+.3f}" for k, v in pairs.items()]
    return [{"label": f"ambiguous: {label}", "effects": group, "correlation": pairs, "sigma": sig,
             "resolution": res,
             "joint_values": {PARAMS[i][1]: float(nom[i] + x_joint[i] * UNITS[i])
                              for i in _index(set(group))},
             "evidence": evidence, "separating_motion": "; or ".join(motions[:2])}]
