"""The live monitor's settled watch: its CPU share and how fast it sees a gyro bias step.

    .venv/bin/python -m benchmarks.bench_monitor_settled [--repeats 2] [--shares 0.01,0.05]

`make run`'s daemon in-process (640×480 at 50 fps, the simulated payload, monitor reporting only),
70 s per run, runs alternating over the settled shares (0.05 = the full share: never cheaper). The
calibration in force is the truth until a gyro bias step of (15, −10, 0) mrad/s at 30 s of payload
time. Per run: when the monitor first settled, its CPU share over 20–30 s (settled, before the step),
and after the step when it left its settled watch and when its estimate came within 5 mrad/s of the
step on x and y. Prints a table; numbers quoted go to benchmarks/results/payload.md by hand.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time

import numpy as np

from benchmarks.yardstick import yardstick_line
from sim.gyro_model import GyroDrift
from thermod.runtime import config
from thermod.runtime.daemon import Daemon

STEP_T = 30.0
STEP = (0.015, -0.010, 0.0)
RUN_S = 70.0
TRACK_TOL = 0.005


@dataclasses.dataclass(frozen=True)
class BiasStep(GyroDrift):
    """No drift until `STEP_T` s of payload time, then a constant extra bias `STEP` (rad/s)."""

    def bias(self, t) -> np.ndarray:
        t = np.asarray(t, np.float64)[..., None]
        return np.where(t >= STEP_T, np.asarray(STEP), 0.0)


def one_run(settled_share: float) -> dict:
    d = Daemon(config.load(None, {"publish.endpoint": f"ipc://{tempfile.gettempdir()}/thermod-settled-{os.getpid()}",
                                  "monitor.settled_cpu_share": settled_share}))
    d.payload.drift = BiasStep()
    d.start()
    t0, rows = time.monotonic(), []
    try:
        while time.monotonic() - t0 < RUN_S:
            d.tick()
            time.sleep(0.25)
            e = d.monitor.estimate()
            rows.append((time.monotonic() - t0, d.monitor.settled,
                         None if e is None else e["gyro_bias_rad_s"][:2], d.monitor.cpu_share()))
    finally:
        d.stop()
    after = [r for r in rows if r[0] >= STEP_T]
    first = next((r[0] for r in rows if r[1]), None)
    settled_before = any(r[1] for r in rows if r[0] < STEP_T)
    share = [r[3] for r in rows if 20.0 <= r[0] < STEP_T and r[3] is not None]
    return {"share": settled_share, "first_settled_s": first,
            "cpu": 100 * float(np.median(share)) if share else None,
            "woke_s": next((r[0] - STEP_T for r in after if not r[1]), None) if settled_before else None,
            "tracked_s": next((r[0] - STEP_T for r in after if r[2] is not None
                               and all(abs(r[2][k] - STEP[k]) < TRACK_TOL for k in (0, 1))), None),
            "counters": dict(d.monitor.counters)}


def _f(x, digits=1) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--shares", default="0.01,0.05", help="settled CPU shares to alternate")
    args = ap.parse_args(argv)
    shares = [float(s) for s in args.shares.split(",")]
    print(yardstick_line())
    print("| settled share | first settled s | monitor CPU % (20–30 s) | left the watch after s | "
          "tracked the step after s | fits | pairs |")
    print("|---|---|---|---|---|---|---|")
    for _ in range(args.repeats):
        for s in shares:
            r = one_run(s)
            c = r["counters"]
            print(f"| {s:g} | {_f(r['first_settled_s'])} | {_f(r['cpu'], 2)} | {_f(r['woke_s'])} | "
                  f"{_f(r['tracked_s'])} | {c.get('fits', 0)} | {c.get('pairs_registered', 0)} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
