"""Speed of the simulator (the fine-time detector renderer and `thermod sim`).

    .venv/bin/python benchmarks/bench_sim.py [--repeats N] [--quick]

Cases (the paper's camera: 640×480, IFOV 0.0391°, τ = 8 ms, 50 Hz; steps ≤ 0.5 px, Eq. 12):
  frame-5tau-100dps   one frame with a 5τ history at 100 °/s (render only)      target ≤ 1 s
  frame-8tau-roll     one frame, 8τ history, 60 °/s yaw + 90 °/s roll           (no target)
  sphere-view         one 640×480 view sampled from the sphere (remap)          (no target)
  sim-2s-50Hz         `thermod sim` of 2 s at 50 Hz, pan:50, real scene,         target ≤ 2 min
                      paper gyro, written to a recording (--quick: 0.5 s)
Prints medians (with min–max) and whether the target is met.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".numba_cache"))

import numpy as np  # noqa: E402

from thermod.physics.calibration import Calibration  # noqa: E402
from thermod.sim import detector, motion, scenes  # noqa: E402


def timeit(fn, repeats: int) -> np.ndarray:
    fn()                                   # warm up (numba cache load, OpenCV threads)
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t0
    return out


def fmt(s: float) -> str:
    return f"{s * 1e3:8.1f} ms" if s < 1 else f"{s:8.2f} s "


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="fewer repeats, 0.5 s simulation")
    args = ap.parse_args(argv)
    reps = 2 if args.quick else args.repeats

    cal = Calibration()
    tex = scenes.load_scene("real", (cal.height, cal.width), 0)
    sc = detector.SphereScene(tex, cal.fx, cal.fy)
    rows = []

    def frame_case(name, mot, history, target):
        traj = motion.Trajectory(motion.parse(mot), 10.0, 9.8, 10.01)
        info = {}

        def run():
            info["r"] = detector.render(sc, traj, [10.0], cal, history_tau=history)
        t = timeit(run, reps)
        rows.append((name, t, target, f"{info['r'].n_steps} steps, max {info['r'].max_step_px:.2f} px/step"))

    frame_case("frame-5tau-100dps", "pan:100", 5.0, 1.0)
    frame_case("frame-8tau-roll", motion.Pan((0.0, np.radians(60), np.radians(90))), 8.0, None)
    t = timeit(lambda: sc.view(np.eye(3), cal.K, cal.width, cal.height), max(reps, 5))
    rows.append(("sphere-view", t, None, "numba maps + cv2.remap"))

    seconds = 0.5 if args.quick else 2.0
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "sim.h5"
        cmd = [sys.executable, "-m", "thermod.cli", "sim", "-o", str(out), "--scene", "real", "--motion",
               "pan:50", "--seconds", str(seconds), "--gyro", "paper", "--no-progress"]
        import subprocess

        times = []
        for _ in range(1 if args.quick else 2):
            t0 = time.perf_counter()
            p = subprocess.run(cmd, capture_output=True, text=True)
            times.append(time.perf_counter() - t0)
            if p.returncode:
                print(p.stderr, file=sys.stderr)
                return 1
        size = out.stat().st_size / 1e6
    rows.append((f"sim-{seconds:g}s-50Hz", np.array(times), 120.0 * seconds / 2.0,
                 f"{p.stdout.strip().split(': ', 1)[-1]}; file {size:.0f} MB"))

    print(f"{'case':<20} {'median':>11} {'min':>11} {'max':>11}  {'target':>9}  notes")
    ok = True
    for name, t, target, note in rows:
        med = float(np.median(t))
        tgt = "" if target is None else (f"≤{target:g} s " + ("ok" if med <= target else "MISS"))
        ok &= target is None or med <= target
        print(f"{name:<20} {fmt(med)} {fmt(t.min())} {fmt(t.max())}  {tgt:>9}  {note}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
