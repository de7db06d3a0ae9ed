"""Shared fixtures. `require(ok, what)` skips a test that needs a real component which is missing,
and fails it instead under THERMOD_STRICT=1 (CI), so nothing real is silently skipped there."""

import os
import sys
from pathlib import Path

import pytest

from thermod.sim.scenes import shared_data_dir

# tests share harnesses with the benchmarks (benchmarks.chaos): the repository root is importable
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

STRICT = os.environ.get("THERMOD_STRICT") == "1"
# $THERMOD_SHARED_DATA, else the first shared/data above the checkout (the lookup thermod.sim uses);
# a path that does not exist when there is none, so `.exists()` checks and `require` skip.
SHARED_DATA = shared_data_dir() or Path(os.environ.get("THERMOD_SHARED_DATA") or "/nonexistent/shared/data")


def _require(ok: bool, what: str) -> None:
    if ok:
        return
    if STRICT:
        pytest.fail(f"THERMOD_STRICT=1 and a real component is missing: {what}")
    pytest.skip(f"missing real component: {what}")


@pytest.fixture
def require():
    return _require


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """shared/data (real thermal frames and gyro log); check `.exists()` before use."""
    return SHARED_DATA


def pytest_collection_modifyitems(config, items):
    """Modules marked `heavy(minutes)` first, longest first, each file's tests kept together and in
    order: `make test` gives whole files to two workers in collection order (--dist loadfile
    --no-loadscope-reorder), so the long analysis files start at once and the short ones fill in
    around them, instead of one long file running alone at the end."""
    def minutes(item) -> float:
        m = item.get_closest_marker("heavy")
        return float(m.args[0]) if m is not None and m.args else 0.0
    items.sort(key=lambda item: -minutes(item))      # stable: file and test order kept otherwise
