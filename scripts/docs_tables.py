"""Rewrite the generated tables of docs/models.md (between their ``<!-- ... table ... -->`` markers) from
``deliffas.models.model_table``; run after adding a model or a preset row: ``python scripts/docs_tables.py``.
With ``--check`` it only reports (exit 1) a table that differs."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from deliffas.models.model_table import model_table_markdown, preset_table_markdown

DOC = Path(__file__).resolve().parents[1] / "docs" / "models.md"
TABLES = {"model table": model_table_markdown, "preset table": preset_table_markdown}


def rewritten(text: str) -> str:
    """``text`` with every generated table replaced by its current markdown."""
    for name, make in TABLES.items():
        pattern = re.compile(rf"(<!-- {name}: [^>]*-->\n).*?(\n<!-- end {name} -->)", re.S)
        if not pattern.search(text):
            raise SystemExit(f"{DOC}: no '<!-- {name}: ... -->' / '<!-- end {name} -->' markers")
        text = pattern.sub(lambda m: m.group(1) + make() + m.group(2), text)
    return text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="only report a table that differs (exit 1)")
    args = p.parse_args(argv)
    text = DOC.read_text(encoding="utf-8")
    new = rewritten(text)
    if new == text:
        return 0
    if args.check:
        print(f"{DOC}: a generated table is out of date; run python scripts/docs_tables.py", file=sys.stderr)
        return 1
    DOC.write_text(new, encoding="utf-8")
    print(f"rewrote the tables of {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
