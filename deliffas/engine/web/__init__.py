"""The avatar as a static web page (``deliffas export --web``): the export and the player's files.

:func:`export_web` writes the folder; :mod:`.model_pack` says which variants the player renders and packs the
U-Nets and the MLP; :mod:`.scene_pack` packs the mesh, atlas tables, cameras and motion; :mod:`.bundle` is the
binary file of arrays. The player itself (``player/``: ES modules and WebGL2 shaders, no dependencies) is package
data; docs/web.md describes it.
"""

from deliffas.engine.web.export import PLAYER_FILES, WEB_FORMAT, export_web
from deliffas.engine.web.model_pack import supported_variants

__all__ = ["export_web", "supported_variants", "PLAYER_FILES", "WEB_FORMAT"]
