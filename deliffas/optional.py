"""Heavy or optional libraries imported at call time, through one door: :func:`import_optional`.

A Ctrl-C that lands while an extension module initialises (open3d's and other pybind11 modules take
seconds) does not arrive as ``KeyboardInterrupt``: pybind11 turns it into ``ImportError("initialization
failed")`` with the interrupt as its cause. Reported as a missing package, it would send a user to
reinstall a library that is there; :func:`import_optional` gives it back as ``KeyboardInterrupt``, so the
command line reports an interruption (exit 130) and how to resume.

A shared leaf: importable from any layer, importing no deliffas layer.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from types import ModuleType
from typing import Any

__all__ = ["import_optional", "interrupted_import", "lazy_exports"]


def interrupted_import(err: BaseException) -> bool:
    """True when ``err`` is, or was caused by, a ``KeyboardInterrupt`` (its cause and context chain)."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def import_optional(module: str, need: str) -> ModuleType:
    """``importlib.import_module(module)``.

    Args:
        module: dotted module name, e.g. ``"open3d"``.
        need: the message when it does not import: who needs it and what to install.

    Raises:
        ImportError: ``need`` (the original error as its cause) when the module does not import.
        KeyboardInterrupt: a Ctrl-C during the import, also one an extension reported as an ImportError.
    """
    try:
        return importlib.import_module(module)
    except ImportError as err:
        if interrupted_import(err):
            raise KeyboardInterrupt from None
        raise ImportError(f"{need} ({type(err).__name__}: {err})") from err


def lazy_exports(package: str, homes: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for a package that exports the names of ``homes`` (name -> its module) and
    imports a module only when one of its names is first used (PEP 562), so importing the package stays light.

    Example (in a package's ``__init__``): ``__getattr__, __dir__ = lazy_exports(__name__, _HOMES)``.
    """
    def __getattr__(name: str) -> Any:
        module = homes.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    def __dir__() -> list[str]:
        return sorted(homes)

    return __getattr__, __dir__
