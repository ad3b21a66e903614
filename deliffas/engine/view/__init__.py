"""``deliffas view``: an interactive free-viewpoint viewer in the browser (built on viser).

A capture without a model (``deliffas view SUBJECT``) opens :mod:`.subject`'s capture viewer instead:
cameras with their images, the posed template, and the silhouette check per camera and frame.

:mod:`deliffas.engine.view_config` holds the settings (outside this package, so the CLI reads them without
viser or torch), :mod:`.scene` what is looked at (runs, cameras, timeline),
:mod:`.renderer` the GUI-free request -> image renderer and its stale-dropping worker thread, and
:mod:`.server` the viser wiring (viser itself is imported only when a server starts).
"""

from __future__ import annotations

from deliffas.engine.view_config import SubjectViewConfig, ViewConfig
from deliffas.engine.view.server import serve as view
from deliffas.engine.view.subject import is_capture, serve_subject as view_subject

__all__ = ["ViewConfig", "SubjectViewConfig", "view", "view_subject", "is_capture"]
