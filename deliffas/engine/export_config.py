"""What ``export_avatar`` writes (:class:`ExportConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from deliffas.options import opt, path_with_suffix

__all__ = ["ExportConfig"]


@dataclass(frozen=True)
class ExportConfig:
    """One run written as one ``.avatar`` file (:func:`deliffas.engine.avatar.export_avatar`)."""

    run: Path = opt(help="run directory written by 'deliffas train'", flag="")
    out: Path = opt(help="the avatar file to write (.avatar)", flag="", parse=path_with_suffix(".avatar"))
    overwrite: bool = opt(False, help="replace an existing OUT")
    """Without it an existing ``out`` is refused."""
