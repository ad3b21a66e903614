"""What ``export_avatar`` and ``export_web`` write (:class:`ExportConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from deliffas.options import opt, positive_int

__all__ = ["ExportConfig", "avatar_file_or_folder"]


def avatar_file_or_folder(text: str) -> Path:
    """An argparse type: a path ending in ``.avatar``, or one without a suffix (the folder of ``--web``)."""
    p = Path(text)
    if p.suffix and p.suffix.lower() != ".avatar":
        raise argparse.ArgumentTypeError(f"expected a file ending in .avatar, or a folder with --web, got {text!r}")
    return p


@dataclass(frozen=True)
class ExportConfig:
    """One run written as one ``.avatar`` file (:func:`deliffas.engine.avatar.export_avatar`), or with ``web`` as
    a static web page that plays it (:func:`deliffas.engine.web.export_web`)."""

    run: Path = opt(help="run directory written by 'deliffas train' (with --web also an .avatar file)", flag="")
    out: Path = opt(help="the avatar file to write (.avatar); with --web the folder to write",
                    flag="", parse=avatar_file_or_folder)
    overwrite: bool = opt(False, help="replace an existing OUT (without it an existing OUT is refused)")
    web: bool = opt(False, help="write OUT as a static web page (index.html, player, weights) that plays the "
                                "avatar in a browser with WebGL2; serve it with 'python -m http.server'")
    motion: Path | None = opt(None, help="with --web: the motion the page plays (.motion or AMASS .npz)",
                              default_text="the capture's test motion")
    frames: int | None = opt(None, help="with --web: at most this many frames of the motion", parse=positive_int,
                             default_text="300")

    def __post_init__(self) -> None:
        suffix = Path(self.out).suffix.lower()
        if self.web and suffix:
            raise ValueError(f"out: --web writes a folder; give a path without a suffix, got {self.out}")
        if not self.web and suffix != ".avatar":
            raise ValueError(f"out: an avatar file must end in .avatar, got {self.out}")
        if not self.web and (self.motion is not None or self.frames is not None):
            raise ValueError("motion, frames: only with --web (an .avatar file holds no motion)")
