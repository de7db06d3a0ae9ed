"""Other stretches of the real log than test_discrepancy_flight_effects.py's roll-dominated one (from
1.0 s), same setup (640×480, 1 s, analysed at a working width of 160):

- from 9.0 s pitch turns as much as roll (41 / 1 / 46 °/s RMS about camera x / y / z): there the first
  scene canvas absorbs most of a scale error, and the flight's extreme poses reach the canvas's edge;
- from 12.0 s the flight pitches almost alone (72 / 1 / 5 °/s): a misalignment's weakly excited
  direction;
- from 30.0 s all three axes turn (43 / 22 / 44 °/s), the canvas sees new scene all the time: a clipped
  gyro and a flat-field step, both missed there before (benchmarks/results/discrepancy.md, "Two more
  stretches")."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from flight_recordings import (  # noqa: E402
    REAL_LOG,
    assert_named_from_flight,
    clipping_range,
    flight_motion,
    flight_recording,
)

from thermod.physics.geometry import so3_log  # noqa: E402

pytestmark = pytest.mark.heavy(10)     # CPU minutes on one core (measured 4.8 + 1.9 + 1.6 + 0.8)
SIZE, SECONDS, WORK_WIDTH, START_S = (640, 480), 1.0, 160, 9.0
SCALE = (1.04, 0.97, 1.05)


def _observable_scale_within(ana, fitted, truth, tol: float) -> bool:
    off = np.abs(fitted.scale_vector / truth.scale_vector - 1)
    hidden = {int(n[6]) for n in ana.unobservable.get("gyro_scale", [])}     # "scale[i]"
    return all(off[i] < tol for i in range(3) if i not in hidden)


@pytest.mark.slow
def test_a_scale_error_the_first_canvas_absorbs_is_named(require):
    """The fit on the first canvas finds 1.003 for a 4–5 % error; before the projection rebuilt the
    scene it was named gyro_bias. Measured: common 1.041 (the pitch-axis factor is unobservable),
    gap 0.0619 → 0.0149 (floor 0.0090)."""
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")
    assert_named_from_flight(f"gyro_scale@{START_S}", {"gyro_scale": SCALE},
                             ("gyro_scale", "gyro_bias", "misalignment", "time_offset"),
                             lambda a, c, t: _observable_scale_within(a, c, t, 0.02),
                             seconds=SECONDS, size=SIZE, work_width=WORK_WIDTH)


@pytest.mark.slow
def test_the_true_model_keeps_its_pixels_where_the_flight_reaches_the_scene_edge(require):
    """The valid mask is made under the nominal model; with a 5 % scale error the true model moves the
    extreme frames' views by a few pixels, and with a 2 px margin they left the known scene: the truth
    measured gap 0.0485 against a floor of 0.0091, and no search could name it. With the motion-only
    margin (`problem.MOTION_MARGIN_RAD`, 5 px here): 0.0128."""
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")
    from thermod.calib import discrepancy as D
    from thermod.calib.discrepancy.problem import Problem, mask_margin_px

    fr = flight_recording({"gyro_scale": SCALE}, seconds=SECONDS, size=SIZE, real_log=True,
                          log_start_s=START_S)
    d = D.prepare(fr.rec, fr.nominal, name="edge", work_width=WORK_WIDTH)
    problem = Problem([d])
    assert mask_margin_px(d) == 5
    nominal, truth = D.Model(fr.nominal), D.Model(fr.truth)
    problem.refresh(nominal)
    gap_nominal = problem.gap(problem.evaluate(nominal).ssr)
    problem.refresh(truth, keep_mask=True, rebuild_scene=True)      # the same pixels, the truth's scene
    gap_truth = problem.gap(problem.evaluate(truth).ssr)
    assert gap_truth < 2.0 * problem.noise_floor(), (gap_truth, problem.noise_floor())
    assert gap_truth < 0.5 * gap_nominal, (gap_truth, gap_nominal)


@pytest.mark.slow
def test_a_misalignment_under_pitch_only_motion_is_recovered_about_every_axis(require):
    """Pitching alone, a misalignment's pitch-axis part shows only through the 5 °/s of roll across it
    (0.5 % of the rate information). Left out as unexcited (a 5 % share was the old cut), its 0.03 rad
    held the fitted y and z at 77 % of the truth and the gap's excess at 0.53 of what it was. Measured
    now (every candidate): (0.0274, −0.0167, 0.0230) rad, gap 0.0660 → 0.0308 (floor 0.0175; the truth's
    0.0301), excess 0.40 of what it was, 117 s."""
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")

    def check(ana, fitted, truth):
        err = np.linalg.norm(so3_log(fitted.R_cam_gyro_matrix @ truth.R_cam_gyro_matrix.T))
        return not ana.unobservable.get("misalignment") and np.degrees(err) < 0.5

    assert_named_from_flight("misalignment@12.0", {"misalignment": (0.03, -0.02, 0.025)},
                             ("misalignment", "gyro_bias", "gyro_scale", "time_offset"), check,
                             seconds=SECONDS, size=SIZE, work_width=WORK_WIDTH)


@pytest.mark.slow
def test_a_clipped_gyro_on_a_three_axis_stretch_is_continued_run_by_run(require):
    """Clipped at 0.7 × the stretch's peak (61.6 °/s): a run of 209 ms mid-flight and two of 136 ms at the
    ends of the series. One continuation gain for all explained 3 % of the excess (fitted at 0.03,
    the slopes of a 1 °/s-quantised log being 0 or ±17.5 rad/s²) and left the flight unexplained.
    With a gain per run: (0.81, 0.27, 1.11) for truth-to-shape ratios of (0.49, 0.13, 1.12), gap 0.0682 →
    0.0126 (floor 0.0054)."""
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")
    level = clipping_range(flight_motion(real_log=True, log_start_s=30.0), SECONDS)

    def check(ana, fitted, truth):
        runs = fitted.gyro_clip_run_gains
        return fitted.gyro_range_rad_s == pytest.approx(level, rel=1e-6) and len(runs) == 3

    assert_named_from_flight("gyro_saturation@30.0", {"gyro_saturation": level},
                             ("gyro_saturation", "gyro_scale", "time_offset"), check,
                             seconds=SECONDS, size=SIZE, work_width=WORK_WIDTH)


@pytest.mark.slow
def test_a_flat_field_step_seen_from_new_views_is_recovered(require):
    """The views after the event see scene the ones before did not, and a canvas made without the step
    takes it in there: the difference of mean residuals gave 3.4 counts for 20. Refined on the
    projected cost: 19.88, gap 0.1221 → 0.0084 (floor 0.0049)."""
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")
    assert_named_from_flight("ffc_event@30.0", {"ffc_event": (0.3, 0.08, 20.0), "fpn": 0.05},
                             ("ffc_event", "time_offset", "detector_nonlinearity"),
                             lambda a, c, t: len(a.model.ffc) == 1
                             and abs(a.model.ffc[0].step_counts - 20.0) < 1.5,
                             seconds=SECONDS, size=SIZE, work_width=WORK_WIDTH)
