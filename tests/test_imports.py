"""The house rule on function-local imports: first-party imports inside function bodies of deliffas/ are at most
``MAX_LOCAL_IMPORTS``, and each states why it cannot be at module level with a ``# local: <reason>`` comment.

Reasons that hold: the light command line (``deliffas --help`` and the config modules import no torch), an import
cycle, an optional heavy dependency loaded at call time, Ctrl-C handling at start-up.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "deliffas"
MAX_LOCAL_IMPORTS = 15
FIRST_PARTY = ("deliffas", "recipes", "benchmarks")
REASON = "# local:"


def _first_party(node: ast.Import | ast.ImportFrom) -> bool:
    if isinstance(node, ast.ImportFrom):
        return node.level > 0 or (node.module or "").split(".")[0] in FIRST_PARTY
    return any(alias.name.split(".")[0] in FIRST_PARTY for alias in node.names)


def local_imports(source: str) -> list[tuple[int, str]]:
    """(line, source lines) of each first-party import statement inside a function body (nested ones once)."""
    lines = source.splitlines()
    found: dict[int, str] = {}
    for fn in ast.walk(ast.parse(source)):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                if isinstance(node, (ast.Import, ast.ImportFrom)) and _first_party(node):
                    found[node.lineno] = "\n".join(lines[node.lineno - 1:node.end_lineno])
    return sorted(found.items())


def _all_local_imports() -> list[tuple[str, int, str]]:
    return [(str(path.relative_to(PACKAGE.parent)), line, text)
            for path in sorted(PACKAGE.rglob("*.py")) for line, text in local_imports(path.read_text())]


def test_the_counter_sees_nested_relative_and_plain_imports():
    source = ("import deliffas\n"
              "def f():\n    from deliffas.options import opt  # local: why\n"
              "    def g():\n        import deliffas.cli\n"
              "    from . import x\n    import json\n")
    assert [line for line, _ in local_imports(source)] == [3, 5, 6]


def test_local_first_party_imports_are_few():
    found = _all_local_imports()
    assert len(found) <= MAX_LOCAL_IMPORTS, (
        f"{len(found)} function-local first-party imports (at most {MAX_LOCAL_IMPORTS}); move one to module level:\n"
        + "\n".join(f"{path}:{line}" for path, line, _ in found))


def test_each_local_import_states_its_reason():
    missing = [f"{path}:{line}: {text.strip()}" for path, line, text in _all_local_imports() if REASON not in text]
    assert not missing, f"function-local imports without a '{REASON} <reason>' comment:\n" + "\n".join(missing)
