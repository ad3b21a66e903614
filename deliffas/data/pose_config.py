"""What ``pose_to_file`` poses and writes (:class:`PoseConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from deliffas.options import non_negative_int, opt, path_with_suffix

__all__ = ["PoseConfig"]


@dataclass(frozen=True)
class PoseConfig:
    """One frame of a motion posing a template, written as a mesh (:func:`deliffas.data.posing.pose_to_file`)."""

    template: Path = opt(help=".character file, or SMPL model .npz/.pkl (official layout)", flag="")
    motion: Path = opt(help=".motion (DDC; its DOF count must match the skeleton) or AMASS .npz (SMPL)", flag="")
    out: Path = opt(help="output mesh, .ply or .obj (.obj keeps the uvs)", parse=path_with_suffix(".ply", ".obj"))
    frame: int = opt(0, help="frame number as written in the motion file (AMASS: the row)", parse=non_negative_int)
    skinning: Literal["dqs", "lbs"] = opt("dqs", help="DDC: dual-quaternion (the original tools' choice) or linear "
                                                     "blend skinning")
    uv: Path | None = opt(None, help="SMPL: OBJ with the model's uv layout",
                          default_text="MODEL_uv.obj next to it, else none needed")
    overwrite: bool = opt(False, help="replace an existing --out file")
