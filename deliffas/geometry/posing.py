"""Posing a character by a motion, from file paths: the API behind ``deliffas pose``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from deliffas.io.dynacap import Character, Motion, ObjData, read_character, read_motion, write_obj
from deliffas.io.files import temp_path
from deliffas.io.text_lines import DynaCapFormatError
from deliffas.geometry.templates import Skinning, build_template, ddc_spec

__all__ = ["pose_frames", "write_posed_mesh"]


def pose_frames(character: Character | str | os.PathLike, motion: Motion | str | os.PathLike,
                frames: list[int] | None = None, skinning: Skinning = "dqs",
                dtype: torch.dtype = torch.float64) -> tuple[np.ndarray, Character]:
    """Posed vertices of ``character`` for the given frame indices of ``motion``.

    Args:
        frames: frame indices as written in the motion file (not row numbers); None = all frames.

    Returns:
        verts (N, V, 3) float64 mm in template vertex order, and the character.
    """
    if not isinstance(character, Character):
        character = read_character(character)
    motion_path = None
    if not isinstance(motion, Motion):
        motion_path = Path(motion)
        motion = read_motion(motion_path, num_dofs=character.skeleton.num_dofs)
    elif motion.dofs.shape[1] != character.skeleton.num_dofs:
        raise ValueError(f"motion has {motion.dofs.shape[1]} DOFs, skeleton has {character.skeleton.num_dofs}")
    if frames is None:
        rows = np.arange(motion.num_frames)
    else:
        try:
            rows = np.array([motion.row_of(f) for f in frames])
        except KeyError as err:
            raise DynaCapFormatError(motion_path or "motion", 0, str(err.args[0])) from None
    template = build_template(ddc_spec(character.path, skinning), dtype=dtype)
    with torch.no_grad():
        verts = template.pose(torch.as_tensor(motion.dofs[rows], dtype=dtype))
    return verts.cpu().numpy().astype(np.float64), character


def write_posed_mesh(path: str | os.PathLike, verts: np.ndarray, character: Character) -> None:
    """Write one posed mesh as ``.obj`` (with the template's per-corner UVs) or ``.ply``, template order."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".obj":
        m = character.mesh
        write_obj(p, ObjData(verts, m.faces, m.uvs, m.face_uvs))
    elif suffix == ".ply":
        import trimesh

        tmp = temp_path(p, keep_suffix=True)
        trimesh.Trimesh(verts, character.mesh.faces, process=False).export(tmp)
        os.replace(tmp, p)
    else:
        raise ValueError(f"output must end in .obj or .ply, got '{p.name}'")
