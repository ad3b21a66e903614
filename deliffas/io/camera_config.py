"""What ``convert_cameras`` reads and writes (:class:`CamerasConfig`); light, so the CLI reads it without numpy
(the format names are asked of the registry when the parser is built)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from deliffas.options import image_size, opt

__all__ = ["CamerasConfig"]


def _writable() -> tuple[str, ...]:
    from deliffas.io.camera_formats import camera_format_names  # local: import cycle, and numpy only when the parser is built

    return camera_format_names()


def _readable() -> tuple[str, ...]:
    return ("auto",) + _writable()


@dataclass(frozen=True)
class CamerasConfig:
    """Cameras read in one format and written in another (:func:`deliffas.io.camera_formats.convert_cameras`)."""

    src: Path = opt(help="camera file or folder to read (for --from-colmap: the .calibration to write)", flag="")
    out: Path | None = opt(None, help="file to write, or an existing folder (it gets the format's usual file name; "
                                      "formats whose cameras are a folder write into it)", flag="", nargs="?",
                           default_text="none; required unless --to-colmap/--from-colmap")
    to_format: str | None = opt(None, help="format to write", flag="--to", choices=_writable,
                                default_text="none; required with OUT")
    from_format: str = opt("auto", help="format of SRC", flag="--from", choices=_readable,
                           default_text="detected from its name")
    size: tuple[int, int] | None = opt(None, help="image size WxH of every camera, for camera files that do not store "
                                                  "it", parse=image_size,
                                       default_text="read from the first image of each camera")
    drop_distortion: bool = opt(False, help="write cameras whose distortion the target cannot hold without it (logged "
                                            "per camera)")
    overwrite: bool = opt(False, help="replace an existing OUT (an empty folder is always replaced)")
    to_colmap: Path | None = opt(None, help="shorthand: SRC --to colmap DIR", metavar="DIR", default_text="not used")
    from_colmap: Path | None = opt(None, help="shorthand: DIR --to dynacap SRC", metavar="DIR",
                                   default_text="not used")
    text: bool = opt(False, help="write the --to format's text variant where it has one (COLMAP: the .txt model "
                                 "instead of .bin); refused for the others")
