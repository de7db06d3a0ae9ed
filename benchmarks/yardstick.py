"""The machine's yardstick: the plain reference K&F's ms per frame on this machine.

    .venv/bin/python -m benchmarks.yardstick [--reps 5]

Every timing in `benchmarks/results/` names it beside itself, so that a number measured on one
machine can be read on another: a payload whose yardstick is 1.5× this machine's runs a solve about
1.5× slower. The yardstick is `bench_deconv.plain_kf` (the reference Matlab algorithm transcribed to
float64 NumPy: K&F α = 2/3, OTF rebuilt per call, six β steps) on a 320×256 frame blurred by a 33 px
comet, λ 2000, one thread, median of `reps` runs after one warm-up. It depends on no thermod solver
code, so an optimisation of thermod never moves it.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from threadpoolctl import threadpool_limits

SHAPE = (256, 320)
KERNEL_PX = 33


def yardstick_ms(reps: int = 5) -> float:
    """Median ms of one plain reference K&F frame (320×256, 33 px comet) on one thread."""
    from benchmarks.bench_deconv import plain_kf, scene
    from thermod.physics.kernels import blur
    from thermod.sim.kernels import comet

    h, w = SHAPE
    big, _ = scene(SHAPE)
    k = comet(KERNEL_PX, KERNEL_PX / 4, 30.0)
    b = blur(big, k)[80:80 + h, 80:80 + w]
    with threadpool_limits(1):
        plain_kf(b, k.weights, k.origin, 2000.0, 2 / 3)
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            plain_kf(b, k.weights, k.origin, 2000.0, 2 / 3)
            times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def yardstick_line(reps: int = 5, ms: float | None = None) -> str:
    """One line for a results file: the yardstick (measured unless `ms` is given), the cores and the
    load average."""
    ms = yardstick_ms(reps) if ms is None else ms
    return (f"yardstick (plain reference K&F, 320×256, `benchmarks/yardstick.py`): {ms:.0f} ms/frame; "
            f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args(argv)
    print(yardstick_line(args.reps))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
