"""The default daemon on this machine and on a slower payload emulated by CPU quotas.

    .venv/bin/python benchmarks/bench_payload.py [--seconds 30] [--repeats 1] [--quick]

`make run`'s configuration (640×480 at 50 fps, the simulated payload), measured from a subscriber in
another process: on every core, then with the daemon and its solver children in a cgroup of 1.2 cores
(60 % of two) and of 1 core (root). Prints the machine's yardstick, the shares deblurred and deblurred
by the temporal rung, latency p50 / p95 / p99, gyro samples lost, what was not deblurred and why, and
where the CPU went per stage (`health.cpu`) with each pipeline stage's latency
(`health.pipeline.stage_ms`). Targets (issue 35): ≥ 99.5 % deblurred, p99 ≤ 60 ms, p95 ≤ 45 ms and
≥ 80 % temporal on two cores; under a quota ≥ 99 % deblurred with p99 ≤ 80 ms and no gyro sample
lost; everything but the solves (and the simulated payload) ≤ 20 % of one core.
"""

from __future__ import annotations

import argparse

from bench_daemon import payload, print_payload


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="15 s runs")
    args = ap.parse_args(argv)
    print_payload(payload(15.0 if args.quick else args.seconds, repeats=args.repeats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
