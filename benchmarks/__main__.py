"""Run the benchmark suites: `python -m benchmarks [NAME ...] [--quick]` from the repository root.

Each suite is a module `benchmarks/bench_NAME.py` that prints its own table; this runs them one
after another as `python -m benchmarks.bench_NAME` (never in parallel: they measure time on a shared
2-core machine).
"""

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def suites() -> dict[str, Path]:
    return {p.stem.removeprefix("bench_"): p for p in sorted(HERE.glob("bench_*.py"))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    ap.add_argument("names", nargs="*", help=f"suites to run (default: all): {', '.join(suites())}")
    ap.add_argument("--quick", action="store_true", help="pass --quick to suites that support it")
    args = ap.parse_args(argv)
    available = suites()
    unknown = [n for n in args.names if n not in available]
    if unknown:
        print(f"unknown suite(s) {unknown}; available: {', '.join(available)}", file=sys.stderr)
        return 2
    failed = []
    for name in args.names or list(available):
        script = available[name]
        quick = args.quick and "--quick" in script.read_text()  # only suites that define the option
        cmd = [sys.executable, "-m", f"benchmarks.{script.stem}"] + (["--quick"] if quick else [])
        print(f"\n## {name}\n", flush=True)
        t0 = time.monotonic()
        rc = subprocess.call(cmd, cwd=HERE.parent)
        print(f"\n({name}: {time.monotonic() - t0:.0f} s, exit {rc})", flush=True)
        if rc:
            failed.append(name)
    if failed:
        print(f"failed suites: {failed}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
