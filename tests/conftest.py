"""Fixtures every folder uses. `require(ok, what)` skips a test that needs a real component which is
missing, and fails it instead under THERMOD_STRICT=1 (CI); the rules live in tests/support. Tests
marked `costly` (analyses of minutes each) are left out of `make test` and checked by
`python -m benchmarks.bench_costly`, which sets THERMOD_COSTLY=1."""

import os
from pathlib import Path

import pytest

from tests import support

pytest_plugins = ("tests.support.cpu_times",)


@pytest.fixture
def require():
    return support.require


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """shared/data (real thermal frames and gyro log); check `.exists()` before use."""
    return support.SHARED_DATA


def pytest_collection_modifyitems(config, items):
    """Modules marked `heavy(minutes)` first, longest first, each file's tests kept together and in
    order: `make test` gives whole files to two workers in collection order (--dist loadfile
    --no-loadscope-reorder), so the long analysis files start at once and the short ones fill in
    around them, instead of one long file running alone at the end."""
    def minutes(item) -> float:
        m = item.get_closest_marker("heavy")
        return float(m.args[0]) if m is not None and m.args else 0.0
    if os.environ.get("THERMOD_COSTLY") != "1":
        costly = [item for item in items if item.get_closest_marker("costly") is not None]
        if costly:
            config.hook.pytest_deselected(items=costly)
            items[:] = [item for item in items if item.get_closest_marker("costly") is None]
    items.sort(key=lambda item: -minutes(item))      # stable: file and test order kept otherwise
