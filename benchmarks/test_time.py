"""CPU time of the test suite, per test, from runs with THERMOD_CPU_TIMES (tests/conftest.py).

    THERMOD_SHARED_DATA=/nonexistent THERMOD_CPU_TIMES=/tmp/before.tsv \\
        .venv/bin/pytest -n 2 --dist loadfile --no-loadscope-reorder        # as `make test`, bare clone
    .venv/bin/python benchmarks/test_time.py /tmp/before.tsv /tmp/after.tsv [--top 10]

Each file holds "seconds<TAB>test id" lines (a test's process time plus the CPU of the child
processes it reaped, setup and teardown included); a later line for the same test replaces an
earlier one, so a second file may hold only the tests that changed. Prints the `--top` slowest tests
of each run and the totals as markdown tables.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def read(path: Path) -> dict[str, float]:
    out: dict[str, float] = {}
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        sec, sep, test = line.partition("\t")
        try:
            out[test] = float(sec)
        except ValueError:
            raise SystemExit(f"{path}:{n}: expected 'seconds<TAB>test id', got {line!r}") from None
        if not sep:
            raise SystemExit(f"{path}:{n}: expected 'seconds<TAB>test id', got {line!r}")
    return out


def by_file(times: dict[str, float]) -> dict[str, float]:
    out: dict[str, float] = {}
    for test, s in times.items():
        f = test.split("::")[0]
        out[f] = out.get(f, 0.0) + s
    return out


def top(times: dict[str, float], n: int) -> str:
    rows = ["| CPU s | test |", "|---:|---|"]
    rows += [f"| {s:.1f} | `{t}` |" for t, s in sorted(times.items(), key=lambda kv: -kv[1])[:n]]
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="THERMOD_CPU_TIMES files, the first the baseline; "
                    "later ones override its tests")
    ap.add_argument("--top", type=int, default=10)
    args = ap.parse_args(argv)
    merged: list[dict[str, float]] = []
    for path in args.runs:
        merged.append({**(merged[-1] if merged else {}), **read(path)})
    for path, times in zip(args.runs, merged, strict=True):
        print(f"## {path.name}: {sum(times.values()) / 60:.1f} CPU-min in {len(times)} tests\n")
        print(top(times, args.top) + "\n")
    files = sorted(set().union(*(by_file(t) for t in merged)), key=lambda f: -by_file(merged[0]).get(f, 0))
    print("| file | " + " | ".join(f"{p.name} CPU s" for p in args.runs) + " |")
    print("|---|" + "---:|" * len(args.runs))
    for f in files[:args.top]:
        print(f"| `{f}` | " + " | ".join(f"{by_file(t).get(f, 0.0):.0f}" for t in merged) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
