"""The core (thermod.physics, io, motion, calib, sync) imports no transport, hardware, simulator or
runtime code: importing every core module in a fresh interpreter must leave those out of sys.modules."""

import pkgutil
import subprocess
import sys
from pathlib import Path

import thermod.calib
import thermod.io
import thermod.motion
import thermod.physics
import thermod.sync

CORE = (thermod.physics, thermod.io, thermod.motion, thermod.calib, thermod.sync)
FORBIDDEN = ("zmq", "gi", "thermod.runtime", "thermod.sim", "thermod.drivers", "thermod.cli",
             "thermod.client", "thermod.batch", "thermod.restore")


def _core_modules() -> list[str]:
    names = []
    for pkg in CORE:
        names.append(pkg.__name__)
        names += [m.name for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")]
    return names


def test_core_imports_no_transport_hardware_or_runtime():
    mods = _core_modules()
    assert len(mods) > 15, mods          # the walk found the subpackages' modules
    code = ("import importlib, sys\n"
            f"for m in {mods!r}: importlib.import_module(m)\n"
            f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN!r} or "
            f"any(m == f or m.startswith(f + '.') for f in {FORBIDDEN!r}))\n"
            "print('\\n'.join(bad))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"the core pulled in: {r.stdout.split()}"


def test_layers_contract_holds():
    """import-linter's `layers` contract (pyproject.toml): every layer imports only the ones below it."""
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, str(root / ".ci" / "lint_imports.py")], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "1 kept, 0 broken" in r.stdout
