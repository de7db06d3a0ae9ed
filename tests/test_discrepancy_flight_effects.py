"""Hidden calibration effects named and recovered from a flight alone (issue 12, goal 3).

What `thermod sim` writes by default and `thermod discrepancy` analyses by default: 640×480 frames,
1 s at 50 Hz, analysed at a working width of 160; the real Betaflight log's attitude from 1.0 s in
(roll-dominated: 5.3 / 1.0 / 57.5 °/s RMS about camera x / y / z), no static lead-in, NETD 50 mK, the
seeded texture; rendered by the simulator's independent fine-time renderer. Each case hides one
effect at the static-path tests' values and asserts what the motion-only search says. Cases marked
"@9" start at 9.0 s in the log, where pitch turns as much as roll (41 / 1 / 46 °/s RMS): there the
first scene canvas absorbs most of a scale error, and the poses reach the canvas's edge.

Each analysis costs 2–8 min of CPU with every candidate, so the search here tries the hidden
effect among the candidates it was confused with before (1–2.2 min each), and the gyro low-pass
(6 min even so) is left to the benchmark: benchmarks/bench_discrepancy.py --flight-effects runs the
same recordings against the whole vocabulary; benchmarks/results/discrepancy.md has that table. The
backward elimination that case relies on is tested in test_discrepancy.py. The real log is
needed: on the synthetic flight of a bare clone these thresholds were not measured.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from thermod.physics.geometry import so3_log

sys.path.insert(0, str(Path(__file__).parent))
from flight_recordings import REAL_LOG, excess, flight_recording  # noqa: E402

SIZE, SECONDS, WORK_WIDTH = (640, 480), 1.0, 160
DEG = np.pi / 180


def _observable_angle_deg(R_fit, R_true, unobservable_axes) -> float:
    """Angle (°) between two rotations, leaving out the directions the motion does not excite."""
    v = so3_log(np.asarray(R_fit) @ np.asarray(R_true).T)
    for axis in unobservable_axes:
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        v = v - a * float(a @ v)
    return float(np.degrees(np.linalg.norm(v)))


def _unobservable_axes(ana) -> list:
    out = []
    for note in ana.unobservable.get("misalignment", []):
        out.append([float(x) for x in note.split("[")[1].split("]")[0].split(",")])
    return out


def _observable_scale_within(ana, fitted, truth, tol: float) -> bool:
    off = np.abs(fitted.scale_vector / truth.scale_vector - 1)
    hidden = {int(n[6]) for n in ana.unobservable.get("gyro_scale", [])}     # "scale[i]"
    return all(off[i] < tol for i in range(3) if i not in hidden)


CASES = {
    # hidden: (simulator effects, rotor vibration °/s RMS, candidates tried, check(ana, fitted, truth))
    # on the log from 1.0 s; "… @9" from 9.0 s
    "gyro_bias": ({"gyro_bias": (0.03, -0.02, 0.015)}, 0.0,
                  ("gyro_bias", "misalignment", "gyro_scale", "time_offset"),
                  # measured (0.0297, −0.0198, 0.0146) rad/s; gap 0.52 → 0.041 at the floor
                  lambda a, c, t: np.all(np.abs(np.subtract(c.bias_rad_s, t.bias_rad_s)) < 0.3 * DEG)),
    "misalignment": ({"misalignment": (0.03, -0.02, 0.025)}, 0.0,
                     ("misalignment", "gyro_bias", "gyro_scale", "time_offset"),
                     # about the roll axis the rotation is barely excited (listed unobservable); the
                     # rest: measured 0.2° off
                     lambda a, c, t: _observable_angle_deg(c.R_cam_gyro_matrix, t.R_cam_gyro_matrix,
                                                           _unobservable_axes(a)) < 1.0),
    "time_constant": ({"time_constant": 0.012}, 0.0,
                      ("time_constant", "optical_psf", "time_offset", "rolling_readout"),
                      lambda a, c, t: abs(c.tau_s / t.tau_s - 1) < 0.10),
    "ffc_event": ({"ffc_event": (0.3, 0.08, 20.0), "fpn": 0.05}, 0.0,
                  ("ffc_event", "time_offset", "detector_nonlinearity"),
                  # one event: the held frames 0.32–0.38 s, then the new NUC's +20 counts
                  lambda a, c, t: len(a.model.ffc) == 1 and abs(a.model.ffc[0].step_counts - 20.0) < 1.5),
    # pitch (41 °/s RMS) and roll both turn: a scale error the first canvas absorbs almost whole (the
    # fit on it: 1.003). Before the projection rebuilt the scene it was named gyro_bias; measured
    # common 1.043, gap 0.0619 → 0.0142 (floor 0.0090)
    "gyro_scale@9": ({"gyro_scale": (1.04, 0.97, 1.05)}, 0.0,
                     ("gyro_scale", "gyro_bias", "misalignment", "time_offset"),
                     lambda a, c, t: _observable_scale_within(a, c, t, 0.02)),
}


@pytest.mark.slow
@pytest.mark.parametrize("hidden", list(CASES))
def test_hidden_effect_is_named_from_a_flight_alone(hidden, require):
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")
    from thermod.calib import discrepancy as D

    effects, vib, candidates, check = CASES[hidden]
    effect, _, start = hidden.partition("@")
    fr = flight_recording(effects, seconds=SECONDS, size=SIZE, real_log=True, vibration_deg_s=vib,
                          log_start_s=float(start) if start else None)
    d = D.prepare(fr.rec, fr.nominal, name=hidden, work_width=WORK_WIDTH)
    ana = D.analyse([d], D.Model(fr.nominal), candidates=candidates)
    assert ana.reference == "motion"
    assert ana.named[:1] == [effect], ana.named
    assert check(ana, ana.model.calib, fr.truth), ana.steps
    assert excess(ana.gap_final, ana.noise_floor) <= 0.5 * excess(ana.gap_initial, ana.noise_floor)
    assert not ana.unexplained, (ana.gap_final, ana.noise_floor)


@pytest.mark.slow
def test_the_true_model_keeps_its_pixels_where_the_flight_reaches_the_scene_edge(require):
    """A second stretch of the log (from 9.0 s: pitch 41 °/s and roll 46 °/s RMS) swings the camera to
    the scene canvas's edge. The valid mask is made under the nominal model; with a 5 % scale error the
    true model moves the extreme frames' views by a few pixels, and with a 2 px margin they left the
    known scene: the truth measured gap 0.0485 against a floor of 0.0091, and no search could name it.
    With the motion-only margin (`problem.MOTION_MARGIN_RAD`, 5 px here): 0.0128."""
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")
    from thermod.calib import discrepancy as D
    from thermod.calib.discrepancy.problem import Problem, mask_margin_px

    fr = flight_recording({"gyro_scale": (1.04, 0.97, 1.05)}, seconds=SECONDS, size=SIZE, real_log=True,
                          log_start_s=9.0)
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
