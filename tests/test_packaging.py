"""The wheel holds every package of the tree: pyproject.toml lists packages explicitly (drivers/, sim/ and
config/ install under thermod.*), so a new subpackage that is not listed would be missing after
`pip install .` while every test run from the editable install still passed."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_directory_is_listed_in_pyproject():
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(tool["packages"])
    dirs = {pkg: ROOT / rel for pkg, rel in tool["package-dir"].items()}
    found = set()
    for pkg, base in dirs.items():
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base)
            found.add(".".join((pkg, *rel.parts)) if rel.parts else pkg)
    assert found - listed == set(), f"missing from pyproject.toml packages: {sorted(found - listed)}"
    assert listed - found == set(), f"listed packages with no directory: {sorted(listed - found)}"
