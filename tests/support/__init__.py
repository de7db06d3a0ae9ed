"""What several test folders share: the real-component check behind the `require` fixture and the
shared-data directory (tests/conftest.py makes fixtures of them), and helper modules beside this one.
Builders the benchmarks use too (flight recordings, sync flights, the reference kernel renderer, the
chaos harness) live in the package, under `thermod.sim` and `thermod.chaos`."""

import os
from pathlib import Path

import pytest

from thermod.sim.scenes import shared_data_dir

STRICT = os.environ.get("THERMOD_STRICT") == "1"
# $THERMOD_SHARED_DATA, else the first shared/data above the checkout (the lookup thermod.sim uses);
# a path that does not exist when there is none, so `.exists()` checks and `require` skip.
SHARED_DATA = shared_data_dir() or Path(os.environ.get("THERMOD_SHARED_DATA") or "/nonexistent/shared/data")


def require(ok: bool, what: str) -> None:
    """Skip a test that needs a real component which is missing; fail it instead under
    THERMOD_STRICT=1 (CI), so nothing real is silently skipped there."""
    if ok:
        return
    if STRICT:
        pytest.fail(f"THERMOD_STRICT=1 and a real component is missing: {what}")
    pytest.skip(f"missing real component: {what}")
