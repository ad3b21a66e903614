"""``deliffas.io`` exports the readers users call, lazily; moved modules keep their old names with a warning."""

from __future__ import annotations

import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import deliffas.io as io_facade


def test_facade_names_resolve_to_their_modules():
    for name in io_facade.__all__:
        obj = getattr(io_facade, name)
        assert obj is getattr(importlib.import_module(io_facade._HOMES[name]), name)
    with pytest.raises(AttributeError):
        io_facade.no_such_reader  # noqa: B018


def test_importing_the_facade_imports_no_format():
    code = "import sys, deliffas.io; print(any(m.startswith('deliffas.io.') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(Path(__file__).resolve().parents[2]), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("old, new", sorted(io_facade.MOVED.items()))
def test_moved_modules_warn_and_keep_their_names(old, new):
    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mod = importlib.import_module(old)
    assert any(issubclass(w.category, DeprecationWarning) and new in str(w.message) for w in caught)
    target = importlib.import_module(new)
    assert all(getattr(mod, n) is getattr(target, n) for n in target.__all__)
