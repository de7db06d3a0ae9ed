"""The costliest checks: the tests marked `costly` (analyses of minutes each on the 2-core CI host),
run here rather than in `make test`, which stays within its time on 2 cores.

    python -m benchmarks.bench_costly [-k EXPR]

Runs `pytest -m costly -rA` on two workers with THERMOD_COSTLY=1, prints a row per test (its outcome
and CPU seconds, from the THERMOD_CPU_TIMES plugin of tests/conftest.py) and exits with pytest's
status: non-zero when any check fails. The real-data cases skip without ../shared/data.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUTCOME = re.compile(r"^(PASSED|FAILED|ERROR|SKIPPED|XFAIL|XPASS) (\S+)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-k", default=None, help="pytest -k expression: a subset of the costly tests")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        cpu_file = Path(tmp) / "cpu.tsv"
        env = {**os.environ, "THERMOD_COSTLY": "1", "THERMOD_CPU_TIMES": str(cpu_file)}
        env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
        cmd = [sys.executable, "-m", "pytest", "-m", "costly", "-n", "2", "--dist", "loadfile", "-q", "-rA",
               "-p", "no:cacheprovider"] + (["-k", args.k] if args.k else [])
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
        outcomes = {}
        for line in proc.stdout:
            sys.stdout.write(line)
            m = OUTCOME.match(line)
            if m:
                outcomes[m.group(2)] = m.group(1).lower()
        rc = proc.wait()
        cpu = {}
        if cpu_file.exists():
            for line in cpu_file.read_text().splitlines():
                sec, _, test = line.partition("\t")
                cpu[test] = float(sec)
    print("\n| test | outcome | CPU s |\n|---|---|---|")
    for test, outcome in outcomes.items():
        print(f"| {test} | {outcome} | {cpu.get(test, float('nan')):.0f} |")
    counts = {o: sum(v == o for v in outcomes.values()) for o in ("passed", "failed", "error", "skipped")}
    print(f"\n{', '.join(f'{n} {o}' for o, n in counts.items())}; "
          f"{sum(cpu.values()) / 60:.1f} CPU-min; pytest exit {rc}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
