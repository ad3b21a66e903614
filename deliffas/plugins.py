"""Entry-point discovery: the modules installed packages declare under a ``deliffas.*`` group, imported once.

A third-party package adds a capture format, a template kind or a model variant by declaring a
module in its ``pyproject.toml``::

    [project.entry-points."deliffas.formats"]      # or "deliffas.templates", "deliffas.variants"
    myformat = "my_package.myformat"

Importing that module registers it, exactly as a built-in module registers itself
(``register_capture_format``, ``register_template_kind``, ``register_variant``). Each registry calls
:func:`load_plugins` with its group before it is first searched. A shared leaf: imports no layer.
"""

from __future__ import annotations

import logging
from importlib.metadata import entry_points

__all__ = ["PluginError", "load_plugins"]

log = logging.getLogger(__name__)

_LOADED: set[str] = set()


class PluginError(ValueError):
    """An installed plug-in that does not import (a ValueError: the command line reports it in one line)."""


def load_plugins(group: str) -> None:
    """Import every entry point of ``group`` (once per group and process).

    Raises:
        PluginError: an entry point that fails to import, naming it, its distribution and what to do.
    """
    if group in _LOADED:
        return
    _LOADED.add(group)
    for ep in entry_points(group=group):
        try:
            ep.load()
        except Exception as err:
            dist = ep.dist.name if ep.dist is not None else "an installed package"
            raise PluginError(f"plug-in {ep.name} = {ep.value} (entry point {group}, from {dist}) does not import: "
                              f"{type(err).__name__}: {err}; fix or uninstall {dist}") from err
        log.debug("loaded plug-in %s = %s (%s)", ep.name, ep.value, group)
