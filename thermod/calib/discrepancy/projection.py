"""Fits on the projected cost of motion-only recordings (variable projection).

Without a static reference the scene canvas S is estimated from the same frames as the calibration,
so the cost of a model is min_S SSR(model, S). A fit on a canvas held fixed stops short: the canvas was
estimated under the old model and has absorbed part of the effect (a 4 % scale error was fitted at
0.3 % on it), and alternating canvas and model crawls along the valley between them. Here each
Levenberg–Marquardt step sees the canvas move with the model (Kaufman's variable projection): the
Jacobian's columns J_i (the frames' change per parameter, canvas held) lose what a canvas change could
explain, J̃_i = J_i − A X_i with X_i = argmin ‖J_i − A X‖ (a few CGLS steps of `SceneOperator`), the
step solves the reduced normal equations J̃ᵀJ̃ δ = J̃ᵀ r, and the canvas moves with it, S − Σ δ_i X_i,
before the usual warm refresh (canvas and FPN) measures the new cost.
"""

from __future__ import annotations

import numpy as np

from thermod.calib.discrepancy import sensor
from thermod.calib.discrepancy.problem import SceneOperator, StepContext


def projected_lm(ctx: StepContext, make, x0, lo, hi, *, h: float = 0.25, iters: int = 3,
                 scene_iters: int = 3, prior=None, min_step: float = 0.02) -> tuple[np.ndarray, float]:
    """Levenberg–Marquardt on the projected cost over x ∈ [lo, hi] (units where `h` moves the image by a
    good fraction of a pixel) from `x0`, the problem holding `make(x0)`'s canvas. `prior` = (x_p, w):
    extra residuals √w (x − x_p) as in `effects._vector_fit`. Returns (x, image SSR) with the problem
    holding x's canvas and FPN (remembered: `Problem.recall`); x0 and the problem as it was when no
    step lowers the cost."""
    problem = ctx.problem
    lo = np.broadcast_to(np.asarray(lo, float), np.shape(x0))
    hi = np.broadcast_to(np.asarray(hi, float), np.shape(x0))
    x = np.clip(np.asarray(x0, float), lo, hi)
    model = make(x)
    ev = problem.evaluate(model, keep=True)
    cost, lam = ev.ssr + _prior_ss(x, prior), 1e-3
    for _ in range(iters if len(x) else 0):
        if problem.exhausted:       # an iteration costs a pass per parameter (one per FFC event)
            break
        J, r, X = projected_jacobian(problem, make, x, ev, h, lo, hi, scene_iters)
        if prior is not None:
            sw = np.sqrt(prior[1]) * np.ones(len(x))
            J = np.vstack([J, np.diag(sw)])
            r = np.concatenate([r, -sw * (x - prior[0])])
        saved, trial = problem.state(), {}

        def cost_at(xn, x=x, saved=saved, X=X, trial=trial):     # this step's trial
            problem.restore(saved)
            for d, Xd in zip(problem.recs, X, strict=True):
                if Xd is not None:      # the canvas follows the step (what J̃ left out)
                    moved = (d.scene - np.tensordot(xn - x, Xd, axes=1)) * (d.fm.support > 0)
                    d.scene = moved.astype(np.float32)
            mn = make(xn)
            problem.refresh(mn, fpn=ctx.fpn, keep_mask=True)
            trial.update(x=xn, model=mn, ev=problem.evaluate(mn, keep=True))
            return trial["ev"].ssr + _prior_ss(xn, prior)

        xn, step, lam = lm_step(-J, r, x, cost_at, lo, hi, lam, c0=cost)
        if step is None:
            problem.restore(saved)
            break
        x_prev = x
        x, model, ev = trial["x"], trial["model"], trial["ev"]      # the accepted trial: the last one
        cost = ev.ssr + _prior_ss(x, prior)
        if np.max(np.abs(x - x_prev)) < min_step:
            break
    problem.remember(model)
    return x, ev.ssr


def lm_step(J, r0, x, cost, lo, hi, lam: float, c0: float | None = None):
    """One damped Gauss–Newton step on the residuals r0 (Jacobian J = ∂r/∂x) that lowers `cost` below
    `c0` (default ‖r0‖²), x kept in [lo, hi]: (new x, step, λ), or (x, None, λ) after 4 dampings."""
    c0 = float(r0 @ r0) if c0 is None else c0
    g, A = J.T @ r0, J.T @ J
    for _ in range(4):
        step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
        xn = np.clip(x + step, lo, hi)
        if cost(xn) < c0:
            return xn, step, lam / 3
        lam *= 10
    return x, None, lam


def _prior_ss(x, prior) -> float:
    return 0.0 if prior is None else float(prior[1] @ (np.asarray(x) - prior[0]) ** 2)


def projected_jacobian(problem, make, x, ev, h, lo, hi, scene_iters):
    """The residual vector r over the masked pixels, its Jacobian −∂r/∂x with the canvas's share
    projected out (J̃, one column per parameter) and per recording the canvas directions X (None for a
    static reference, which does not move)."""
    models = []
    for i in range(len(x)):
        e = np.zeros(len(x))
        e[i] = h if x[i] + h <= hi[i] else -h
        models.append((e[i], make(x + e)))
    cols, rs, Xs = [[] for _ in x], [], []
    model = make(x)
    for k, d in enumerate(problem.recs):
        p0 = ev.predicted[k]
        rs.append(ev.residuals[k][d.mask].astype(np.float64))
        op = SceneOperator(d, model, live=sensor.segments(d, model) >= 0) if d.reference == "motion" else None
        Xd = []
        for i, (step, m_i) in enumerate(models):
            p1, _ = sensor.predict(d, m_i)
            Ji = ((p1 - p0) / np.float32(step)) * d.mask
            if op is not None:
                Xi = op.solve(Ji, np.zeros_like(d.scene, np.float64), scene_iters)
                Ji = Ji - op.apply(Xi) * d.mask
                Xd.append(Xi)
            cols[i].append(Ji[d.mask].astype(np.float64))
        Xs.append(np.stack(Xd) if Xd else None)
    J = np.stack([np.concatenate(c) for c in cols], axis=1) if len(x) else np.zeros((0, 0))
    return J, np.concatenate(rs), Xs
