"""Writing one mesh as ``.obj`` (with per-corner uvs) or ``.ply``, in the given vertex order, atomically."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from jaxtyping import Float, Integer, Real

from deliffas.checks import finite_as
from deliffas.io.infra.files import durable_replace, temp_path
from deliffas.io.obj import ObjData, write_obj

__all__ = ["MESH_SUFFIXES", "write_mesh"]

MESH_SUFFIXES = (".obj", ".ply")


def write_mesh(path: str | os.PathLike, verts: Real[np.ndarray, "V 3"], faces: Integer[np.ndarray, "F 3"],
               uvs: Float[np.ndarray, "T 2"] | None = None, face_uvs: Integer[np.ndarray, "F 3"] | None = None) -> Path:
    """Write ``verts`` (V, 3) and ``faces`` (F, 3); ``.obj`` keeps ``uvs`` (T, 2) / ``face_uvs`` (F, 3).

    Raises:
        ValueError: another suffix, or vertices that are not finite in the file (a mesh nobody can open).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"output must end in .obj or .ply, got '{p.name}'")
    if suffix == ".obj":  # write_obj refuses non-finite values itself
        write_obj(p, ObjData(verts, np.asarray(faces), np.zeros((0, 2)) if uvs is None else uvs, face_uvs))
        return p
    import trimesh  # heavy: only the .ply path needs it

    tmp = temp_path(p, keep_suffix=True)
    verts = finite_as(f"{p}: vertices", verts, np.float32)  # a PLY stores float32: 1e307 mm would be inf
    trimesh.Trimesh(verts, np.asarray(faces), process=False).export(tmp)
    durable_replace(tmp, p)
    return p
