"""Fits on the projected cost of a motion-only recording (`thermod.calib.discrepancy.projection`).

Without a static lead-in the scene canvas is estimated from the same frames as the calibration; a
canvas estimated under the nominal model has absorbed part of a calibration error, so a fit that
holds it fixed stops short. The projected fit moves the canvas with every step.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from thermod.sim.flight_recordings import flight_recording

# checked by benchmarks/bench_costly.py rather than make test (1.7 CPU-min on the CI host)
pytestmark = [pytest.mark.heavy(2), pytest.mark.costly]      # CPU minutes on one core (measured 2.0)

SCALE = (1.05, 0.96, 1.04)


@pytest.fixture(scope="module")
def flight():
    from thermod.calib import discrepancy as D
    from thermod.calib.discrepancy.problem import Problem, StepContext

    # the synthetic multirotor attitude (no ../shared needed): 1 s, all three axes turning
    fr = flight_recording({"gyro_scale": SCALE}, seconds=1.0, size=(320, 240))
    d = D.prepare(fr.rec, fr.nominal, name="scale", work_width=160)
    assert d.reference == "motion"
    problem = Problem([d])
    nominal = D.Model(fr.nominal)
    problem.refresh(nominal)
    ctx = StepContext.at(problem, problem.evaluate(nominal, keep=True), (), 0.05)
    return problem, ctx, nominal, fr.truth, problem.state()


def test_a_projected_fit_recovers_what_the_fixed_canvas_absorbed(flight):
    from thermod.calib.discrepancy import EFFECTS

    problem, ctx, nominal, truth, start = flight
    problem.restore(start)
    fixed = EFFECTS["gyro_scale"].fit(ctx, nominal)
    problem.restore(start)
    projected = EFFECTS["gyro_scale"].fit(dataclasses.replace(ctx, project=True), nominal)
    assert problem.recall(projected.model)          # the problem holds the canvas it was fitted with
    observed = [i for i in range(3) if f"scale[{i}]" not in projected.unobservable]
    err_fixed = np.abs(fixed.model.calib.scale_vector / truth.scale_vector - 1)[observed]
    err_proj = np.abs(projected.model.calib.scale_vector / truth.scale_vector - 1)[observed]
    # measured: (1.0485, 0.9600, 1.0190) for (1.05, 0.96, 1.04) in three steps (about the roll axis,
    # which the canvas follows most, it converges slowest); the fixed canvas's fit: (1.016, 0.988, 0.834)
    assert err_proj.max() < 0.5 * err_fixed.max(), (err_proj, err_fixed)
    assert err_proj.max() < 0.03, projected.model.calib.scale
    assert problem.gap(projected.ssr) < problem.gap(fixed.ssr)


def test_a_projected_fit_started_at_the_truth_stays_there(flight):
    from thermod.calib.discrepancy import EFFECTS
    from thermod.calib.discrepancy.data import Model

    problem, ctx, nominal, truth, start = flight
    problem.restore(start)
    model = Model(truth)
    problem.refresh(model, keep_mask=True, rebuild_scene=True)
    ssr = problem.evaluate(model).ssr
    for name in ("time_offset", "gyro_scale"):
        f = EFFECTS[name].fit(dataclasses.replace(ctx, project=True), model)
        assert f.ssr <= ssr
        assert abs(f.model.calib.time_offset_s - truth.time_offset_s) < 5e-4
        assert np.abs(f.model.calib.scale_vector / truth.scale_vector - 1).max() < 0.01
