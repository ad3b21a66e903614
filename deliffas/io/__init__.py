"""File formats: every reader and writer of deliffas, returning plain records.

The bottom layer: modules here import no other deliffas layer (only the shared leaves such as
``deliffas.checks``, ``deliffas.native`` and ``deliffas.optional``). Units stay as the files have them; each reader's
docstring states them.

The readers and writers users call most are importable from here (``from deliffas.io import read_cameras``);
each is imported from its module on first use, so ``import deliffas.io`` stays light. Names that moved keep
their old module for one release, with a ``DeprecationWarning`` naming the new home (:data:`MOVED`).
"""

from typing import TYPE_CHECKING

from deliffas.optional import lazy_exports

if TYPE_CHECKING:  # the names for type checkers and the API docs; at run time __getattr__ imports them
    from deliffas.io.avatar_file import read_avatar_file, write_avatar_file
    from deliffas.io.camera_formats import camera_format_names, convert_cameras, read_cameras, write_cameras
    from deliffas.io.cameras import Camera
    from deliffas.io.formats.dynacap.calibration import read_calibration, write_calibration
    from deliffas.io.formats.dynacap.character import read_character, read_motion
    from deliffas.io.formats.dynacap.meshes import read_meshes
    from deliffas.io.motion import Motion
    from deliffas.io.video import read_video_info, write_video

_HOMES = {
    "Camera": "deliffas.io.cameras",
    "Motion": "deliffas.io.motion",
    "camera_format_names": "deliffas.io.camera_formats",
    "convert_cameras": "deliffas.io.camera_formats",
    "read_avatar_file": "deliffas.io.avatar_file",
    "read_calibration": "deliffas.io.formats.dynacap.calibration",
    "read_cameras": "deliffas.io.camera_formats",
    "read_character": "deliffas.io.formats.dynacap.character",
    "read_meshes": "deliffas.io.formats.dynacap.meshes",
    "read_motion": "deliffas.io.formats.dynacap.character",
    "read_video_info": "deliffas.io.video",
    "write_avatar_file": "deliffas.io.avatar_file",
    "write_calibration": "deliffas.io.formats.dynacap.calibration",
    "write_cameras": "deliffas.io.camera_formats",
    "write_video": "deliffas.io.video",
}

MOVED = {"deliffas.io.calibration": "deliffas.io.formats.dynacap.calibration",
         "deliffas.io.meshes": "deliffas.io.formats.dynacap.meshes"}
"""Old module -> new module of names that moved (the old modules re-export them with a DeprecationWarning)."""

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
