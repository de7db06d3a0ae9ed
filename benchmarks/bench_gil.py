"""A temporal solve beside threads that run Python: in the worker's thread, and in a child process.

The daemon's other threads (scheduler, gyro driver, monitor, publisher, camera) run Python for a
good share of the time. A solve in a thread takes the GIL back after each of its GIL-free calls
(FFTW, numba, OpenCV) and waits there until the holder's switch interval runs out; a solve in a
child process (`thermod.runtime.solvers.InChild`) has a GIL of its own. This times the 640×480
temporal rung over a 6×8 kernel grid (the roll of the warm-up) alone and beside `--hogs` threads
that each run pure Python for `--duty` of the time in 1.3 ms stretches, with the daemon's switch
interval (1 ms).

    .venv/bin/python benchmarks/bench_gil.py [--solves 30] [--hogs 2] [--duty 0.3]

Prints the median wall time per solve (and, in the thread, its CPU time).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import threading
import time

import numpy as np

from thermod.physics.calibration import Calibration
from thermod.restore.plan import make_deconvolver, render
from thermod.restore.settings import DeblurConfig
from thermod.runtime.governor import ladder
from thermod.runtime.pipeline import PRIOR_FRAMES
from thermod.runtime.solvers import InChild, InThread, Layout, SharedFrames, slots_needed, warm_gyro

H, W = 480, 640
CAL = Calibration(width=W, height=H, fx=800.0, fy=800.0, cx=319.5, cy=239.5, frame_rate_hz=50.0)
DEBLUR = DeblurConfig(mode="grid", grid=(6, 8))


@dataclasses.dataclass
class Settings:
    deblur: DeblurConfig
    calib: Calibration


class Hogs:
    """Threads running pure Python `duty` of the time."""

    def __init__(self, n: int, duty: float):
        self.n, self.duty, self.stop = n, duty, threading.Event()
        self.threads = [threading.Thread(target=self._run, daemon=True) for _ in range(n)]

    def _run(self):
        busy = 0.0013
        idle = busy * (1 - self.duty) / self.duty
        while not self.stop.is_set():
            t = time.perf_counter()
            while time.perf_counter() - t < busy:
                pass
            time.sleep(idle)

    def __enter__(self):
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        for t in self.threads:
            t.join()


def timed(solver, n: int) -> tuple[float, float]:
    """Median wall and thread-CPU ms (the caller's) of `n` temporal solves, each with one prior."""
    tg, rate = warm_gyro(CAL)
    k, _ = render(tg, rate, CAL, 0.0, DEBLUR)
    yy, xx = np.mgrid[:H, :W]
    img = (8000.0 + 200.0 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
           + np.random.default_rng(0).normal(0.0, 10.0, (H, W))).astype(np.float32)
    rung, s = ladder(DEBLUR)[0], Settings(DEBLUR, CAL)
    first = solver.solve(s, rung, img, k, -0.02, (tg, rate), lambda: None).estimate
    walls, cpus = [], []
    for _ in range(n + 3):
        c0 = time.thread_time()
        got = solver.solve(s, rung, img, k, 0.0, (tg, rate), lambda: first)
        cpus.append(time.thread_time() - c0)
        walls.append(got.seconds)
        if got.prior_frames != 1:
            raise SystemExit("the solve found no prior")
        if hasattr(got.estimate, "release"):
            got.estimate.release()
    if hasattr(first, "release"):
        first.release()
    return 1e3 * statistics.median(walls[3:]), 1e3 * statistics.median(cpus[3:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--solves", type=int, default=30)
    ap.add_argument("--hogs", type=int, default=2)
    ap.add_argument("--duty", type=float, default=0.3)
    args = ap.parse_args(argv)
    sys.setswitchinterval(0.001)
    import cv2
    from threadpoolctl import threadpool_limits
    cv2.setNumThreads(1)
    threadpool_limits(1)
    frames = SharedFrames(Layout((H, W), 1, slots_needed(1, PRIOR_FRAMES), 4 * H * W))
    child = InChild(make_deconvolver, frames, 0)
    rows = []
    try:
        for where, solver in (("thread", InThread(make_deconvolver)), ("child process", child)):
            alone = timed(solver, args.solves)
            with Hogs(args.hogs, args.duty):
                beside = timed(solver, args.solves)
            rows.append((where, alone, beside))
    finally:
        child.close()
        frames.close()
    print(f"640×480 temporal solve over a 6×8 grid, median of {args.solves}; beside {args.hogs} threads "
          f"running Python {100 * args.duty:.0f} % of the time each; GIL switch interval 1 ms")
    print("| solve in | alone: wall ms | beside: wall ms | ratio | thread CPU ms alone / beside |")
    print("|---|---|---|---|---|")
    for where, a, b in rows:
        cpu = f"{a[1]:.1f} / {b[1]:.1f}" if where == "thread" else "– (another process)"
        print(f"| {where} | {a[0]:.1f} | {b[0]:.1f} | {b[0] / a[0]:.2f} | {cpu} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
