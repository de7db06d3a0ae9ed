"""`thermod bench`: run the benchmark suites of a source checkout (benchmarks/ is not installed)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from thermod.errors import ThermodError


def add_arguments(parser) -> None:
    parser.add_argument("names", nargs="*", help="suites to run (default: all)")
    parser.add_argument("--quick", action="store_true", help="shorter runs where a suite supports it")


def checkout_root() -> Path | None:
    """The source checkout holding benchmarks/: the working directory or one above it, else the checkout
    this package is installed from (editable install: thermod/cli/bench.py → parents[2])."""
    here = Path.cwd().resolve()
    for root in (here, *here.parents, Path(__file__).resolve().parents[2]):
        if (root / "benchmarks" / "__main__.py").is_file() and (root / "thermod" / "__init__.py").is_file():
            return root
    return None


def run(args) -> int:
    root = checkout_root()
    if root is None:
        raise ThermodError("benchmarks/ not found: run `thermod bench` inside a source checkout of thermod "
                           f"(looked in {Path.cwd()} and above, and next to {Path(__file__).parents[1]})")
    cmd = [sys.executable, "-m", "benchmarks", *args.names] + (["--quick"] if args.quick else [])
    return subprocess.call(cmd, cwd=root)
