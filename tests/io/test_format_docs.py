"""The camera formats the docs list are the registered ones: a format added without its docs fails here."""

from __future__ import annotations

import re
from pathlib import Path

from deliffas.io.camera_formats import camera_format_names

REPO = Path(__file__).resolve().parents[2]


def _names(text: str) -> tuple[str, ...]:
    return tuple(re.findall(r"`([a-z0-9_]+)`", text))


def test_readme_cameras_row_lists_every_format():
    row = next(line for line in (REPO / "README.md").read_text(encoding="utf-8").splitlines()
               if line.startswith("| `deliffas cameras "))
    listed = row.split("capture formats (", 1)[1].split(";", 1)[0]
    assert _names(listed) == camera_format_names()


def test_data_md_lists_and_tabulates_every_format():
    text = (REPO / "docs" / "data.md").read_text(encoding="utf-8")
    listed = text.split("(`camera_format_names()`:", 1)[1].split(";", 1)[0]
    assert _names(listed) == camera_format_names()  # in detection order
    table = text.split("| format | files |", 1)[1].split("\n\n", 1)[0]
    rows = [line.split("|")[1].strip() for line in table.splitlines()[2:] if line.startswith("|")]
    assert sorted(rows) == sorted(camera_format_names())
