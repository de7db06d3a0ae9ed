"""Run import-linter's contracts (pyproject.toml [tool.importlinter]) on the source tree.

The installed package maps drivers/, sim/ and config/ into thermod.* (pyproject's package-dir); grimp
walks directories, so the check runs on a temporary tree of symlinks laid out as the installed package.
Exit status is lint-imports'.
"""

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAPPED = {"drivers": "drivers", "sim": "sim", "configs": "config"}   # thermod.<name> → <dir>


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="thermod-layers-") as tmp:
        pkg = Path(tmp) / "thermod"
        pkg.mkdir()
        for entry in (ROOT / "thermod").iterdir():
            if entry.name != "__pycache__":
                (pkg / entry.name).symlink_to(entry)
        for name, src in MAPPED.items():
            (pkg / name).symlink_to(ROOT / src)
        env = {**os.environ, "PYTHONPATH": tmp, "PYTHONDONTWRITEBYTECODE": "1"}
        exe = Path(sys.executable).with_name("lint-imports")
        cmd = [str(exe) if exe.exists() else "lint-imports", "--no-cache", str(ROOT / "pyproject.toml")]
        # run outside the checkout: `import thermod` then finds the symlink tree
        return subprocess.run(cmd, env=env, cwd=tmp).returncode


if __name__ == "__main__":
    sys.exit(main())
