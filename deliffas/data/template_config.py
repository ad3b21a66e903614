"""Which template variants ``build_templates`` writes, and their shells (:class:`TemplateConfig`); light, so the
CLI reads it without numpy."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from deliffas.options import opt

__all__ = ["TemplateConfig"]


@dataclass(frozen=True)
class TemplateConfig:
    """The template variants of one character with their outer shells
    (:func:`deliffas.data.template_build.build_templates`)."""

    character: Path = opt(help=".character file", flag="")
    out: Path = opt(help="output folder (out/<variant>/ per variant, out/report.json)")
    smooth_iters: int | None = opt(None, help="also a Taubin-smoothed variant (ITERS lambda/mu pairs)", flag="--smooth",
                                   metavar="ITERS", default_text="none")
    coarse_faces: int | None = opt(None, help="also a decimated variant with about FACES faces", flag="--coarse",
                                   metavar="FACES", default_text="none")
    offset_mm: float = opt(30.0, help="outer-shell offset d in mm", flag="--offset", metavar="MM")
    safe: bool = opt(False, help="limit d per vertex where the shell would cross another part")
    atlas_res: int = opt(512, help="xatlas packing resolution of new atlases and texel grid of the report", metavar="R")
    overwrite: bool = opt(False, help="replace an earlier 'deliffas template' output in --out (a non-empty one is "
                                      "refused otherwise)")
