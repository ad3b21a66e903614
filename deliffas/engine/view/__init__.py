"""``deliffas view``: an interactive free-viewpoint viewer in the browser (built on viser).

A capture without a model (``deliffas view SUBJECT``) opens :mod:`.subject`'s capture viewer instead:
cameras with their images, the posed template, and the silhouette check per camera and frame.

:mod:`.config` holds the settings, :mod:`.scene` what is looked at (runs, cameras, timeline),
:mod:`.renderer` the GUI-free request -> image renderer and its stale-dropping worker thread, and
:mod:`.server` the viser wiring (imported, with viser, only when :func:`view` runs).
"""

from __future__ import annotations

from deliffas.engine.view.config import SubjectViewConfig, ViewConfig

__all__ = ["ViewConfig", "SubjectViewConfig", "view", "view_subject"]


def view(cfg: ViewConfig) -> None:
    """Serve the viewer until interrupted (see :func:`deliffas.engine.view.server.serve`)."""
    from deliffas.engine.view.server import serve  # viser is optional and heavy: imported when serving

    serve(cfg)


def view_subject(cfg: SubjectViewConfig) -> None:
    """Serve the capture viewer until interrupted (see :func:`deliffas.engine.view.subject.serve_subject`)."""
    from deliffas.engine.view.subject import serve_subject  # viser is imported when serving

    serve_subject(cfg)
