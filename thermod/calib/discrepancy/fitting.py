"""The search tools every candidate effect's fit uses: a one-parameter grid + bounded refinement
(`scalar_fit`), a Levenberg–Marquardt fit of a parameter vector (`vector_fit`), both switching to the
projected cost (the scene canvas moving with the model, `projection`) when the step asks for it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import optimize

from thermod.calib.discrepancy.data import Model
from thermod.calib.discrepancy.problem import StepContext
from thermod.calib.discrepancy.projection import lm_step, projected_lm


def scalar_fit(ctx: StepContext, make, grid, lo, hi, refine_width, x0=None):
    """Coarse grid then bounded Brent refinement of a one-parameter family `make(x) -> Model`.
    A warm context (`StepContext.warm`) with the current value `x0` refines within ±2 grid steps of it
    instead."""
    def cost(x):
        return ctx.problem.evaluate(make(x)).ssr

    if ctx.project and x0 is not None and len(grid) > 1 and ctx.problem.has_motion_reference:
        step = float(grid[1] - grid[0])        # one unit: a grid step

        def make_u(u):
            return make(float(x0 + step * u[0]))
        u, ssr = projected_lm(ctx, make_u, np.zeros(1), (lo - x0) / step, (hi - x0) / step,
                              iters=ctx.project_iters)
        return float(x0 + step * u[0]), ssr
    if ctx.warm and x0 is not None and len(grid) > 1:
        step = float(grid[1] - grid[0])
        a, b = max(lo, x0 - 2 * step), min(hi, x0 + 2 * step)
        c0 = cost(x0)
        res = optimize.minimize_scalar(cost, bounds=(a, b), method="bounded",
                                       options={"xatol": (b - a) * 5e-3, "maxiter": 10})
        return (float(res.x), float(res.fun)) if res.fun < c0 else (float(x0), c0)
    costs = [cost(x) for x in grid]
    i = int(np.argmin(costs))
    a = max(lo, grid[max(i - 1, 0)] if refine_width is None else grid[i] - refine_width)
    b = min(hi, grid[min(i + 1, len(grid) - 1)] if refine_width is None else grid[i] + refine_width)
    if b <= a:
        return grid[i], costs[i]
    res = optimize.minimize_scalar(cost, bounds=(a, b), method="bounded",
                                   options={"xatol": (b - a) * 2e-3, "maxiter": 15})
    if res.fun < costs[i]:
        return float(res.x), float(res.fun)
    return float(grid[i]), float(costs[i])


def vector_fit(ctx: StepContext, make, x0s, unit, bound, iters: int = 6, h: float = 0.25, prior=None):
    """Levenberg–Marquardt on the residual vector from the best of several starts (x in `unit`s).

    The Jacobian is a forward difference with a step of `h` units: the forward model is only
    smooth down to its resampling precision, so steps must move the image by a good fraction of
    a pixel, not by float rounding. `prior` = (x_p, w): an independent measurement x_p of x with
    weight w (SSR units per unit²) appended as extra residuals √w (x − x_p). Returns the fitted
    parameters and the image SSR alone (what the selection compares).
    """
    problem = ctx.problem

    def residuals(x):
        p = np.zeros(0) if prior is None else np.sqrt(prior[1]) * (x - prior[0])
        return np.concatenate([problem.residual_vector(make(x * unit)), p])

    def cost(x):
        r = residuals(x)
        return float(r @ r)

    if ctx.project and problem.has_motion_reference:
        x, ssr = projected_lm(ctx, lambda u: make(u * unit), np.asarray(x0s[0], float), -bound, bound,
                              h=h, prior=prior, iters=ctx.project_iters)
        return x * unit, ssr
    x = min((np.clip(np.asarray(x0, float), -bound, bound) for x0 in x0s), key=cost)
    lam = 1e-3
    for _ in range((min(iters, 2) if ctx.warm else iters) if len(x) else 0):
        if problem.exhausted:       # an iteration costs a pass per parameter (one per FFC event)
            break
        r0 = residuals(x)
        J = np.empty((len(r0), len(x)))
        for i in range(len(x)):
            e = np.zeros(len(x))
            e[i] = h if x[i] + h <= bound else -h
            J[:, i] = (residuals(x + e) - r0) / e[i]
        x, step, lam = lm_step(J, r0, x, cost, -bound, bound, lam)
        if step is None or np.max(np.abs(step)) < 0.02:
            break
    return x * unit, problem.evaluate(make(x * unit)).ssr


def with_calib(model: Model, **changes) -> Model:
    """`model` with its calibration's fields `changes` replaced."""
    return dataclasses.replace(model, calib=model.calib.replace(**changes))


def current_ssr(ctx: StepContext, model: Model) -> float:
    """The image SSR of `model` in this step."""
    return ctx.problem.evaluate(model).ssr
