"""Each option's help is stated once: an ``opt(..., help=...)`` field of deliffas/ carries no field docstring too
(reference detail beyond the help belongs in the help or the class docstring)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "deliffas"


def doubled_fields(source: str) -> list[str]:
    """``Class.field`` of each ``opt(...)`` field followed by a string literal (its field docstring)."""
    found = []
    for cls in ast.walk(ast.parse(source)):
        if isinstance(cls, ast.ClassDef):
            for field, after in zip(cls.body, cls.body[1:]):
                if (isinstance(field, ast.AnnAssign) and isinstance(field.value, ast.Call)
                        and getattr(field.value.func, "id", getattr(field.value.func, "attr", None)) == "opt"
                        and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                        and isinstance(after.value.value, str)):
                    found.append(f"{cls.name}.{field.target.id}")
    return found


def _doubled() -> dict[str, list[str]]:
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        fields = doubled_fields(path.read_text())
        if fields:
            found[path.relative_to(PACKAGE).as_posix()] = fields
    return found


def test_the_check_finds_a_field_docstring_after_opt():
    source = ('class C:\n    a: int = opt(1, help="a")\n    """A again."""\n'
              '    b: int = 2\n    """Not an option: a docstring is its only text."""\n'
              '    c: int = options.opt(3, help="c")\n    """C again."""\n')
    assert doubled_fields(source) == ["C.a", "C.c"]


def test_no_option_states_its_help_twice():
    found = _doubled()
    assert not found, ("opt fields with a field docstring as well as help= (fold it into the help or the "
                       f"class docstring): {found}")
