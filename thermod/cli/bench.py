"""`thermod bench`: run the benchmark suites of a source checkout (benchmarks/ is not installed)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from thermod.errors import ThermodError


def add_arguments(parser) -> None:
    parser.add_argument("names", nargs="*", help="suites to run (default: all)")
    parser.add_argument("--quick", action="store_true", help="shorter runs where a suite supports it")


def run(args) -> int:
    root = Path(__file__).resolve().parents[1]
    if not (root / "benchmarks" / "__main__.py").exists():
        raise ThermodError(f"benchmarks/ not found next to {root / 'thermod'}: run from a source checkout")
    cmd = [sys.executable, "-m", "benchmarks", *args.names] + (["--quick"] if args.quick else [])
    return subprocess.call(cmd, cwd=root)
