"""``deliffas view``: an interactive free-viewpoint viewer in the browser (built on viser).

:mod:`.config` holds the settings, :mod:`.scene` what is looked at (runs, cameras, timeline),
:mod:`.renderer` the GUI-free request -> image renderer and its stale-dropping worker thread, and
:mod:`.server` the viser wiring (imported, with viser, only when :func:`view` runs).
"""

from __future__ import annotations

from deliffas.engine.view.config import ViewConfig

__all__ = ["ViewConfig", "view"]


def view(cfg: ViewConfig) -> None:
    """Serve the viewer until interrupted (see :func:`deliffas.engine.view.server.serve`)."""
    from deliffas.engine.view.server import serve  # viser is optional and heavy: imported when serving

    serve(cfg)
