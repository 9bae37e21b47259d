"""The README's commands are what CI runs: keep them the same."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    ci = [
        line
        for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if "pytest" in line and not line.startswith("#")
    ]
    assert len(ci) == 1, ".ci/run must run pytest on exactly one line"
    assert ci[0].strip() in readme, f"README must show the command .ci/run runs: {ci[0]}"


def test_readme_starts_with_the_two_commands():
    readme = (ROOT / "README.md").read_text()
    head = readme[: readme.find("## ", readme.find("## ") + 3)]
    assert "drape demo" in head and "pytest" in head
