"""The machine's yardstick: the plain reference K&F's ms per frame on this machine.

    .venv/bin/python -m benchmarks.yardstick [--reps 5] [--jitter-s 10]

Every timing in `benchmarks/results/` names it beside itself, so that a number measured on one
machine can be read on another: a payload whose yardstick is 1.5× this machine's runs a solve about
1.5× slower. The yardstick is `bench_deconv.plain_kf` (the reference Matlab algorithm transcribed to
float64 NumPy: K&F α = 2/3, OTF rebuilt per call, six β steps) on a 320×256 frame blurred by a 33 px
comet, λ 2000, one thread, median of `reps` runs after one warm-up. It depends on no thermod solver
code, so an optimisation of thermod never moves it.

`host_jitter` says how steady the host is: a fixed FFT pair (640×480, one thread) timed in thread CPU
time every 10 ms, as the daemon's workers run, alone on the machine. Its p99 / p50 is the factor by
which the host itself stretches 1 % of any work, so a latency p99 on this host is at least that
factor times the median work on a frame's path.
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


JITTER_SHAPE = (480, 640)
JITTER_GAP_S = 0.010            # idle between runs, like a worker between frames
JITTER_OUTLIER = 2.5            # a run this many times the median is an outlier


def host_jitter(seconds: float = 10.0) -> dict:
    """``{"p50_ms", "p99_ms", "ratio", "outliers"}``: the thread CPU time of one fixed FFT pair
    (`JITTER_SHAPE`, float32, one thread) run every `JITTER_GAP_S` for `seconds`; ``ratio`` is
    p99 / p50 and ``outliers`` the share of runs over `JITTER_OUTLIER` × the median."""
    img = np.random.default_rng(0).random(JITTER_SHAPE, dtype=np.float32)
    cpu = []
    with threadpool_limits(1):
        np.fft.irfft2(np.fft.rfft2(img), s=JITTER_SHAPE)
        end = time.monotonic() + seconds
        while time.monotonic() < end or len(cpu) < 100:
            c0 = time.thread_time()
            np.fft.irfft2(np.fft.rfft2(img), s=JITTER_SHAPE)
            cpu.append(time.thread_time() - c0)
            time.sleep(JITTER_GAP_S)
    a = 1e3 * np.asarray(cpu)
    p50, p99 = float(np.median(a)), float(np.percentile(a, 99))
    return {"p50_ms": p50, "p99_ms": p99, "ratio": p99 / p50,
            "outliers": float(np.mean(a > JITTER_OUTLIER * p50)), "runs": len(a)}


def jitter_line(j: dict | None = None, seconds: float = 10.0) -> str:
    """One line for a results file: the host's jitter (`host_jitter`, measured unless `j` is given)."""
    j = host_jitter(seconds) if j is None else j
    return (f"host jitter (`benchmarks/yardstick.py`, a fixed FFT pair's CPU time every 10 ms, alone): "
            f"p50 {j['p50_ms']:.2f} ms, p99 ×{j['ratio']:.1f}, {100 * j['outliers']:.1f} % of runs "
            f"over ×{JITTER_OUTLIER:g}")


def yardstick_line(reps: int = 5, ms: float | None = None) -> str:
    """One line for a results file: the yardstick (measured unless `ms` is given), the cores and the
    load average."""
    ms = yardstick_ms(reps) if ms is None else ms
    return (f"yardstick (plain reference K&F, 320×256, `benchmarks/yardstick.py`): {ms:.0f} ms/frame; "
            f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--jitter-s", type=float, default=10.0, help="seconds of the host-jitter runs (0: none)")
    args = ap.parse_args(argv)
    print(yardstick_line(args.reps))
    if args.jitter_s > 0:
        print(jitter_line(seconds=args.jitter_s))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
