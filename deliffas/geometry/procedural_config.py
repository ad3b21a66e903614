"""What ``make_procedural_character`` builds and where (:class:`ProceduralConfig`); light, so the CLI reads it
without numpy."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from deliffas.options import opt

__all__ = ["ProceduralConfig"]


@dataclass(frozen=True)
class ProceduralConfig:
    """The procedural character written as a DynaCap character folder
    (:func:`deliffas.geometry.procedural.make_procedural_character`)."""

    out_dir: Path = opt(help="folder to write (created)", flag="")
    seed: int = opt(0, help="proportions, colours and patterns")
    target_faces: int = opt(8000, help="template face budget", flag="--faces")
    name: str = opt("procedural", help="file stem (<name>.character, ...)")
    texture_size: int = opt(1024, help="texture atlas side in texels")
    overwrite: bool = opt(False, help="replace an earlier procedural character in OUT_DIR")
