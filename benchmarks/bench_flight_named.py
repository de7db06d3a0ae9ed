"""Hidden effects named from real-log flights: the costliest cases, checked here rather than in
`make test` (each is 2.5–5 CPU-min on the 2-core CI host; the suite keeps one case per stretch and
effect family, tests/calib/test_discrepancy_flight_effects.py and _stretch.py).

    .venv/bin/python benchmarks/bench_flight_named.py [--cases NAME,...]

Each case is `thermod.sim.flight_recordings.assert_named_from_flight` with the values the tests had
(640×480, 1 s, analysed at a working width of 160): the effect is named first, its check holds, the
gap's excess over the floor is at least halved and nothing is left unexplained. Prints a row per case
(pass or the assertion, CPU s) and exits 1 when any case fails. Needs ../shared/data (the real
Betaflight log).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))

import numpy as np  # noqa: E402

from thermod.physics.geometry import so3_log  # noqa: E402
from thermod.sim.flight_recordings import (  # noqa: E402
    REAL_LOG,
    assert_named_from_flight,
    clipping_range,
    flight_motion,
)

SIZE, SECONDS, WORK_WIDTH = (640, 480), 1.0, 160
DEG = np.pi / 180


def _observable_scale_within(ana, fitted, truth, tol: float) -> bool:
    off = np.abs(fitted.scale_vector / truth.scale_vector - 1)
    hidden = {int(n[6]) for n in ana.unobservable.get("gyro_scale", [])}     # "scale[i]"
    return all(off[i] < tol for i in range(3) if i not in hidden)


def _misalignment_within(ana, fitted, truth, deg: float) -> bool:
    err = np.linalg.norm(so3_log(fitted.R_cam_gyro_matrix @ truth.R_cam_gyro_matrix.T))
    return not ana.unobservable.get("misalignment") and np.degrees(err) < deg


def _observable_angle_deg(R_fit, R_true, unobservable_axes) -> float:
    """Angle (°) between two rotations, leaving out the directions the motion does not excite."""
    v = so3_log(np.asarray(R_fit) @ np.asarray(R_true).T)
    for axis in unobservable_axes:
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        v = v - a * float(a @ v)
    return float(np.degrees(np.linalg.norm(v)))


def _unobservable_axes(ana) -> list:
    return [[float(x) for x in note.split("[")[1].split("]")[0].split(",")]
            for note in ana.unobservable.get("misalignment", [])]


def _clipped_runs(level: float):
    return lambda ana, fitted, truth: abs(fitted.gyro_range_rad_s / level - 1) < 1e-6 and \
        len(fitted.gyro_clip_run_gains) == 3


def cases() -> dict:
    """name → (hidden "effect@start", simulator effects, candidates, check(ana, fitted, truth))."""
    level = clipping_range(flight_motion(real_log=True, log_start_s=30.0), SECONDS)
    return {
        # measured (0.0297, −0.0198, 0.0146) rad/s; gap 0.52 → 0.041 at the floor
        "gyro_bias@1.0": ("gyro_bias", {"gyro_bias": (0.03, -0.02, 0.015)},
                          ("gyro_bias", "misalignment", "gyro_scale", "time_offset"),
                          lambda a, c, t: np.all(np.abs(np.subtract(c.bias_rad_s, t.bias_rad_s))
                                                 < 0.3 * DEG)),
        "misalignment@1.0": ("misalignment", {"misalignment": (0.03, -0.02, 0.025)},
                             ("misalignment", "gyro_bias", "gyro_scale", "time_offset"),
                             # the roll axis holds 0.9 % of the rate information: fitted too
                             lambda a, c, t: _observable_angle_deg(c.R_cam_gyro_matrix, t.R_cam_gyro_matrix,
                                                                   _unobservable_axes(a)) < 1.0),
        # pitch turns as much as roll: the first canvas absorbs most of a scale error (common 1.041)
        "gyro_scale@9.0": ("gyro_scale@9.0", {"gyro_scale": (1.04, 0.97, 1.05)},
                           ("gyro_scale", "gyro_bias", "misalignment", "time_offset"),
                           lambda a, c, t: _observable_scale_within(a, c, t, 0.02)),
        # pitching alone: the pitch-axis part shows only through 5 °/s of roll across it
        "misalignment@12.0": ("misalignment@12.0", {"misalignment": (0.03, -0.02, 0.025)},
                              ("misalignment", "gyro_bias", "gyro_scale", "time_offset"),
                              lambda a, c, t: _misalignment_within(a, c, t, 0.5)),
        # clipped at 0.7 × the stretch's peak: three runs, a continuation gain each
        "gyro_saturation@30.0": ("gyro_saturation@30.0", {"gyro_saturation": level},
                                 ("gyro_saturation", "gyro_scale", "time_offset"), _clipped_runs(level)),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    all_cases = cases() if REAL_LOG else {}
    ap.add_argument("--cases", default=",".join(all_cases), help="comma-separated case names")
    args = ap.parse_args(argv)
    if not REAL_LOG:
        print("no ../shared/data (the real Betaflight log): nothing to run")
        return 0
    names = [n for n in args.cases.split(",") if n]
    unknown = [n for n in names if n not in all_cases]
    if unknown:
        raise SystemExit(f"--cases: unknown {unknown}; known: {', '.join(all_cases)}")
    print("| case | result | CPU s |\n|---|---|---|", flush=True)
    failed = 0
    for name in names:
        hidden, effects, candidates, check = all_cases[name]
        c0 = time.process_time()
        try:
            assert_named_from_flight(hidden, effects, candidates, check, seconds=SECONDS, size=SIZE,
                                     work_width=WORK_WIDTH)
            result = "pass"
        except AssertionError as e:
            failed += 1
            result = f"FAIL: {str(e)[:200]}"
        print(f"| {name} | {result} | {time.process_time() - c0:.0f} |", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
