"""The wheel holds every package of the tree: pyproject.toml lists packages explicitly (drivers/, sim/ and
config/ install under thermod.*), so a new subpackage that is not listed would be missing after
`pip install .` while every test run from the editable install still passed."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


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


def test_license_is_an_spdx_expression_with_its_file():
    """PEP 639: the `license = { text = ... }` table is deprecated (setuptools stops accepting it in
    February 2027); an SPDX expression plus license-files is the form that lasts."""
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    project = pyproject["project"]
    assert project["license"] == "MIT"
    assert project["license-files"] and all((ROOT / f).is_file() for f in project["license-files"])
    assert "MIT License" in (ROOT / "LICENSE").read_text()
    build = pyproject["build-system"]["requires"]
    assert any(r.replace(" ", "").startswith("setuptools>=") and
               int(r.split(">=")[1].split(".")[0]) >= 77 for r in build), build
