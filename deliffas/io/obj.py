"""Wavefront OBJ reading and writing in the template's own vertex order with per-corner UVs.

The template OBJ's ``v`` lines define the vertex order used everywhere in deliffas; UV seams live in
per-corner indices (``face_uvs``), vertices are never split (trimesh's default loader would).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import no_type_check

import numpy as np
from jaxtyping import Float, Integer

from deliffas.checks import finite_as
from deliffas.io.infra.text_lines import DynaCapFormatError, read_text, write_text_atomic

__all__ = ["ObjData", "read_obj", "write_obj"]


@dataclass(frozen=True)
class ObjData:
    """A triangle mesh as an OBJ file holds it.

    Attributes:
        verts: (V, 3) float64, file units (mm for DynaCap), in the file's ``v`` order.
        faces: (F, 3) int64, 0-based indices into ``verts``.
        uvs: (T, 2) float64 texture coordinates in [0, 1]^2 (OBJ convention, v up); (0, 2) when absent.
        face_uvs: (F, 3) int64 per-corner indices into ``uvs`` (seams live here); -1 when the file
            gives none; None when no face has any.
        colors: (V, 3) float64 per-vertex colours in [0, 1], or None.
        normals: (N, 3) float64 ``vn`` vectors (file units, not necessarily unit length), or None.
        face_normals_idx: (F, 3) int64 indices into ``normals``, -1 when absent; or None.
        mtllib: the ``mtllib`` argument, or None.
        material: the first ``usemtl`` argument, or None.
    """

    verts: Float[np.ndarray, "V 3"]
    faces: Integer[np.ndarray, "F 3"]
    uvs: Float[np.ndarray, "T 2"] = field(default_factory=lambda: np.zeros((0, 2)))
    face_uvs: Integer[np.ndarray, "F 3"] | None = None
    colors: Float[np.ndarray, "V 3"] | None = None
    normals: Float[np.ndarray, "N 3"] | None = None
    face_normals_idx: Integer[np.ndarray, "F 3"] | None = None
    mtllib: str | None = None
    material: str | None = None

    @property
    def num_verts(self) -> int:
        return int(self.verts.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def has_uvs(self) -> bool:
        return self.face_uvs is not None and len(self.uvs) > 0 and bool((self.face_uvs >= 0).all())


def _parse_floats(path: Path, line_no: int, toks: list[str], n: tuple[int, ...], what: str) -> list[float]:
    if len(toks) not in n:
        want = " or ".join(str(k) for k in n)
        raise DynaCapFormatError(path, line_no, f"expected {want} numbers after '{what}', got {len(toks)}")
    try:
        vals = [float(t) for t in toks]
    except ValueError:
        raise DynaCapFormatError(path, line_no, f"expected numbers after '{what}', got '{' '.join(toks)[:60]}'") from None
    if not np.all(np.isfinite(vals)):
        raise DynaCapFormatError(path, line_no, f"expected finite numbers after '{what}', got NaN or inf")
    return vals


def _face_corners(p: Path, line_no: int, rest: list[str]) -> list[list[int]]:
    """The three corners of an ``f`` line as [v, vt, vn] OBJ indices (0 = absent)."""
    if len(rest) != 3:
        raise DynaCapFormatError(p, line_no, f"expected a triangle (3 corners) after 'f', got {len(rest)} corners")
    corners = []
    for c in rest:
        parts = c.split("/")
        if len(parts) > 3 or not parts[0]:
            raise DynaCapFormatError(p, line_no, f"expected a face corner 'v[/vt[/vn]]', got '{c[:30]}'")
        try:
            idx = [int(x) if x else 0 for x in parts] + [0] * (3 - len(parts))
        except ValueError:
            raise DynaCapFormatError(p, line_no, f"expected integer indices in face corner, got '{c[:30]}'") from None
        if any(abs(i) >= 2**31 for i in idx):
            raise DynaCapFormatError(p, line_no, f"face index out of range in corner '{c[:30]}'")
        corners.append(idx)
    return corners


@no_type_check  # called per face corner: kept out of the test run's type checks
def _resolve(p: Path, line_no: int, i: int, n: int, what: str) -> int:
    """An OBJ index as 0-based: 1-based ones, negative ones counted back from the ``n`` lines so far; 0 (absent)
    -> -1."""
    if i > 0:
        return i - 1
    if i < 0 and n + i < 0:
        raise DynaCapFormatError(p, line_no, f"relative {what} index {i} counts back past the first of "
                                             f"the {n} {what} lines so far")
    return n + i if i < 0 else -1


def _check_face_indices(p: Path, face_lines: list[int], f: np.ndarray, ft: np.ndarray, fn: np.ndarray,
                        num_verts: int, num_uvs: int, num_normals: int) -> None:
    """Every face's vertex index in range, and its uv and normal indices where the file has uvs / normals."""
    bad = np.nonzero((f < 0).any(1) | (f >= num_verts).any(1))[0]
    if len(bad):
        raise DynaCapFormatError(p, face_lines[bad[0]], f"face vertex index out of range 1..{num_verts}")
    if num_uvs:
        bad = np.nonzero((ft >= num_uvs).any(1))[0]
        if len(bad):
            raise DynaCapFormatError(p, face_lines[bad[0]], f"face uv index out of range 1..{num_uvs}")
        bad = np.nonzero((ft < 0).any(1))[0]
        if len(bad):  # a template's atlas needs every corner's uv: a partial one must not pass as complete
            raise DynaCapFormatError(p, face_lines[bad[0]], f"face without a uv index in a file with {num_uvs} "
                                                            "'vt' lines (expected 'f v/vt ...' on every face)")
    if num_normals:
        bad = np.nonzero((fn >= num_normals).any(1))[0]
        if len(bad):
            raise DynaCapFormatError(p, face_lines[bad[0]], f"face normal index out of range 1..{num_normals}")


def read_obj(path: str | os.PathLike) -> ObjData:
    """Read a triangle OBJ keeping the file's ``v`` order and its per-corner UV indices.

    Faces with more than three corners are rejected (DynaCap templates are triangle meshes).
    ``v x y z [r g b]`` colours are kept when every vertex has them.

    Raises:
        DynaCapFormatError: missing file, bad token counts, non-numbers, NaN/inf, out-of-range indices.
    """
    p = Path(path)
    text = read_text(p, "OBJ mesh")
    verts: list[list[float]] = []
    colors: list[list[float]] = []
    uvs: list[list[float]] = []
    normals: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    fuv: list[tuple[int, int, int]] = []
    fvn: list[tuple[int, int, int]] = []
    face_lines: list[int] = []
    mtllib = material = None
    for line_no, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] == "#":
            continue
        toks = line.split()
        key, rest = toks[0], toks[1:]
        if key == "v":
            vals = _parse_floats(p, line_no, rest, (3, 4, 6, 7), "v")
            if len(vals) in (3, 4):
                verts.append(vals[:3])
            else:
                verts.append(vals[:3])
                colors.append(vals[3:6] if len(vals) == 6 else vals[4:7])
        elif key == "vt":
            vals = _parse_floats(p, line_no, rest, (2, 3), "vt")
            uvs.append(vals[:2])
        elif key == "vn":
            normals.append(_parse_floats(p, line_no, rest, (3,), "vn"))
        elif key == "f":
            corners = _face_corners(p, line_no, rest)
            faces.append(tuple(_resolve(p, line_no, c[0], len(verts), "v") for c in corners))
            fuv.append(tuple(_resolve(p, line_no, c[1], len(uvs), "vt") for c in corners))
            fvn.append(tuple(_resolve(p, line_no, c[2], len(normals), "vn") for c in corners))
            face_lines.append(line_no)
        elif key == "mtllib":
            mtllib = " ".join(rest)
        elif key == "usemtl" and material is None:
            material = " ".join(rest)
        # other keys (o, g, s, l, ...) carry nothing deliffas needs
    if not verts:
        raise DynaCapFormatError(p, 0, "expected 'v' lines, found no vertices")
    if not faces:
        raise DynaCapFormatError(p, 0, "expected 'f' lines, found no faces")
    v = np.asarray(verts, dtype=np.float64)
    f, ft, fn = (np.asarray(x, dtype=np.int64) for x in (faces, fuv, fvn))
    _check_face_indices(p, face_lines, f, ft, fn, len(v), len(uvs), len(normals))
    return ObjData(
        verts=v,
        faces=f,
        uvs=np.asarray(uvs, dtype=np.float64).reshape(-1, 2),
        face_uvs=ft if uvs else None,
        colors=np.asarray(colors, dtype=np.float64) if len(colors) == len(verts) and colors else None,
        normals=np.asarray(normals, dtype=np.float64) if normals else None,
        face_normals_idx=fn if normals else None,
        mtllib=mtllib,
        material=material,
    )


def write_obj(path: str | os.PathLike, obj: ObjData, crlf: bool = False, precision: int = 6) -> None:
    """Write ``obj`` so that ``read_obj`` returns equal arrays (to ``precision`` decimals).

    Vertices are written in array order; faces as ``f v/vt[/vn]`` with 1-based indices.

    Raises:
        ValueError: a vertex, colour, normal or uv that is NaN or inf (nothing is written).
    """
    for key in ("verts", "colors", "normals", "uvs"):
        if getattr(obj, key) is not None:
            finite_as(f"{path}: {key}", getattr(obj, key), np.float64)
    fmt = f"%.{precision}f"
    parts: list[str] = ["# written by deliffas"]
    if obj.mtllib:
        parts.append(f"mtllib {obj.mtllib}")
    if obj.colors is not None:
        block = np.concatenate([obj.verts, obj.colors], axis=1)
        parts.append("\n".join("v " + " ".join([fmt] * 6) % tuple(r) for r in block))
    else:
        parts.append("\n".join("v " + " ".join([fmt] * 3) % tuple(r) for r in obj.verts))
    if obj.normals is not None:
        parts.append("\n".join("vn " + " ".join([fmt] * 3) % tuple(r) for r in obj.normals))
    has_uv = obj.face_uvs is not None and len(obj.uvs) > 0
    if has_uv:
        parts.append("\n".join("vt " + " ".join([fmt] * 2) % tuple(r) for r in obj.uvs))
    if obj.material:
        parts.append(f"usemtl {obj.material}")
    f1 = obj.faces + 1
    cols = [f1]
    if has_uv:
        cols.append(obj.face_uvs + 1)
    has_vn = obj.face_normals_idx is not None and obj.normals is not None
    if has_vn:
        if not has_uv:
            cols.append(np.zeros_like(f1))  # placeholder, printed as empty
        cols.append(obj.face_normals_idx + 1)
    corners = np.stack(cols, axis=-1)  # (F, 3, k)
    lines = []
    for face in corners.tolist():
        cs = []
        for c in face:
            if len(c) == 1:
                cs.append(f"{c[0]}")
            elif len(c) == 2:
                cs.append(f"{c[0]}/{c[1]}")
            else:
                cs.append(f"{c[0]}/{c[1] if c[1] > 0 else ''}/{c[2]}")
        lines.append("f " + " ".join(cs))
    parts.append("\n".join(lines))
    write_text_atomic(path, "\n".join(parts) + "\n", crlf=crlf)
