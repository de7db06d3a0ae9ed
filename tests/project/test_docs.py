"""The README stays a reference: its results table is the generated one, it is short before
"Development", and no doc points outside the repository."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def summary(*args: str) -> subprocess.CompletedProcess:
    """`python -m benchmarks.summary --check ARGS` from the repository root (tests import no benchmark)."""
    return subprocess.run([sys.executable, "-m", "benchmarks.summary", "--check", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def test_readme_holds_the_generated_results_table():
    r = summary()
    assert r.returncode == 0, r.stderr       # 1: the table is stale
    rows = [line for line in r.stdout.splitlines() if line.startswith("| ")][1:]    # below the header
    assert len(rows) >= 5


def test_readme_is_short_before_development_and_starts_with_the_two_commands():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    dev = next(i for i, line in enumerate(lines) if re.match(r"^#+ *Development", line))
    assert dev <= 150, f"README.md has {dev} lines before Development"
    block = lines[lines.index("```sh") + 1:]
    assert block[0].startswith("make run") and block[1].startswith("make test") and block[2] == "```"


def test_summary_lines_are_well_formed(tmp_path):
    (tmp_path / "a.md").write_text("# A\n<!-- summary: x | 1 ms | ≤ 2 ms -->\n", encoding="utf-8")
    (tmp_path / "b.md").write_text("<!-- summary: only two | parts -->\n", encoding="utf-8")
    r = summary("--results", str(tmp_path))
    assert r.returncode == 2, "a summary line without three parts was accepted"
    assert "b.md" in r.stderr


def test_docs_do_not_point_outside_the_repository():
    for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = p.read_text(encoding="utf-8")
        assert "../shared" not in text and "shared/DESIGN" not in text, p


def test_interfaces_lists_every_calibration_field():
    import dataclasses

    from thermod.physics.calibration import Calibration

    text = (ROOT / "docs" / "interfaces.md").read_text(encoding="utf-8")
    block = text[text.index("`thermod.physics.calibration.Calibration`"):text.index("Derived:")]
    listed = set(re.findall(r"[A-Za-z_]+", block.split("):", 1)[1]))
    missing = [f.name for f in dataclasses.fields(Calibration) if f.name not in listed]
    assert not missing, f"docs/interfaces.md does not list the Calibration fields {missing}"


def test_the_paper_is_cited_where_eq_numbers_are_explained():
    doi = "doi:10.3390/s22051893"
    assert doi in (ROOT / "docs" / "design.md").read_text(encoding="utf-8")
    assert doi in (ROOT / "thermod" / "physics" / "__init__.py").read_text(encoding="utf-8")
