"""Optional imports (deliffas.optional): a Ctrl-C during an extension's initialisation stays a Ctrl-C.

pybind11 modules (open3d) report an exception raised while they initialise as ``ImportError("initialization
failed")`` with the exception as its cause; the finder below makes an import fail that way, as a Ctrl-C that
lands while ``import open3d`` runs does.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import signal
import sys

import pytest

from deliffas.optional import import_optional, interrupted_import


class _InitFails(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports of ``name`` fail as a pybind11 module's do when ``cause`` is raised during its initialisation."""

    def __init__(self, name: str, cause: BaseException):
        self.name, self.cause = name, cause

    def find_spec(self, fullname, path=None, target=None):
        return importlib.machinery.ModuleSpec(fullname, self) if fullname == self.name else None

    def create_module(self, spec):
        try:
            raise self.cause
        except BaseException as err:
            raise ImportError("initialization failed") from err

    def exec_module(self, module):  # pragma: no cover - create_module always raises
        pass


@pytest.fixture
def failing_import(monkeypatch):
    """``failing_import(name, cause)``: the next ``import name`` fails as above (the real module is restored after)."""
    def install(name: str, cause: BaseException) -> None:
        monkeypatch.delitem(sys.modules, name, raising=False)
        monkeypatch.setattr(sys, "meta_path", [_InitFails(name, cause), *sys.meta_path])
    return install


def test_an_interrupted_initialisation_is_a_keyboard_interrupt(failing_import):
    failing_import("open3d", KeyboardInterrupt())
    from deliffas.geometry.raycast import _o3d

    with pytest.raises(KeyboardInterrupt):
        _o3d()


def test_a_failed_initialisation_names_the_package_and_the_cause(failing_import):
    failing_import("open3d", OSError("libGL.so.1: cannot open shared object file"))
    from deliffas.geometry.raycast import _o3d

    with pytest.raises(ImportError, match="needs the 'open3d' package.*initialization failed"):
        _o3d()
    with pytest.raises(ImportError, match="pip install nothing-here"):
        import_optional("deliffas_no_such_module", "this needs nothing-here: pip install nothing-here")


def test_interrupted_import_follows_causes_and_contexts():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError("initialization failed")  # noqa: B904 - the context, as a C extension sets it
    except ImportError as err:
        assert interrupted_import(err)
    assert not interrupted_import(ImportError("no module named open3d"))


def test_the_command_line_reports_it_as_an_interruption(failing_import, monkeypatch, tmp_path, capsys):
    """``deliffas convert`` interrupted while it imports open3d: exit 130 and the resume line, no 'open3d missing'."""
    from deliffas import cli
    from deliffas.cli import handlers
    from deliffas.geometry.raycast import _o3d

    failing_import("open3d", KeyboardInterrupt())
    monkeypatch.setattr(handlers, "cmd_convert", lambda args: _o3d())
    previous = signal.getsignal(signal.SIGINT)
    try:
        code = cli.main(["convert", str(tmp_path / "capture"), str(tmp_path / "out")])
    finally:
        signal.signal(signal.SIGINT, previous)
    err = capsys.readouterr().err
    assert code == 130 and "open3d" not in err, err
    assert "deliffas convert: interrupted: no shard finished yet; resume with: deliffas convert" in err
