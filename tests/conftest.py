"""Shared fixtures. `require(ok, what)` skips a test that needs a real component which is missing,
and fails it instead under THERMOD_STRICT=1 (CI), so nothing real is silently skipped there."""

import os
from pathlib import Path

import pytest

STRICT = os.environ.get("THERMOD_STRICT") == "1"
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


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
    """../shared/data (real thermal frames and gyro log), when present."""
    return SHARED_DATA
