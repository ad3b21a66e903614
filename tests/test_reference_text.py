"""Docs and code are reference (docs/conventions.md): no dates outside CHANGELOG.md, no paths of the machine
they were written on, no measurements attributed to "this machine" in the docs."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SOURCES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))] + [
    p for folder in ("deliffas", "recipes", "benchmarks", "examples", "scripts")
    for p in sorted((REPO / folder).rglob("*")) if p.suffix in (".py", ".c", ".md", ".sh")]
"""Every file a user reads as reference (CHANGELOG.md, the history, is not among them)."""

DOCS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]

DATE = re.compile(r"(?<![\w-])20\d\d-[01]\d-[0-3]\d(?![\w-])")  # not in file names (pt_inception-2015-12-05-...)
MACHINE_PATH = re.compile(r"(?<![\w.~])/(?:work|root|home|Users)/")
THIS_MACHINE = re.compile(r"\bthis machine\b", re.IGNORECASE)


def _hits(paths: list[Path], pattern: re.Pattern) -> list[str]:
    return [f"{p.relative_to(REPO)}:{i}: {line.strip()}" for p in paths
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if pattern.search(line)]


def test_no_dates_outside_the_changelog():
    assert not _hits(SOURCES, DATE), "dates belong in CHANGELOG.md"


def test_no_machine_paths():
    assert not _hits(SOURCES, MACHINE_PATH), "write paths relative to the repository or as placeholders"


def test_docs_name_the_machine_they_measured_on():
    assert not _hits(DOCS, THIS_MACHINE), "say which machine (cores, CPU), not 'this machine'"
