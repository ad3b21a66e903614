"""DynaCap ``.meshes`` files: a tracked surface per frame, in the template's vertex order (formats doc 1.8)."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, Integer

from deliffas.checks import finite_as
from deliffas.io.infra.text_lines import DynaCapFormatError, TextLines, write_text_atomic

PathLike = str | os.PathLike

__all__ = ["MeshSequence", "read_meshes", "write_meshes", "MESHES_VERSIONS"]

MESHES_VERSIONS = ("v2.1", "v2.0")


@dataclass(frozen=True)
class MeshSequence:
    """A ``.meshes`` sequence: per frame the template's vertices (template order, mm).

    Attributes:
        frames: (N,) int64 frame numbers (v2.0 files: 0..N-1).
        verts: (N, V, 3) float32 mm, template vertex order.
        version: the file's format version (``v2.1`` or ``v2.0``).
    """

    frames: Integer[np.ndarray, "N"]
    verts: Float[np.ndarray, "N V 3"]
    version: str = "v2.1"


def read_meshes(path: PathLike, num_verts: int | None = None) -> MeshSequence:
    """Read a v2.1 (frame index per line) or v2.0 (implicit frames from 0) ``.meshes`` file."""
    t = TextLines(path, what="mesh sequence")
    head = t.next("a 'Skeletool Meshes file <version>' header").split()
    if len(head) < 2 or head[-1] not in MESHES_VERSIONS or head[0] != "Skeletool":
        raise t.error(f"expected header 'Skeletool Meshes file v2.1' (or v2.0), got '{' '.join(head)[:60]}'")
    version = head[-1]
    frames, rows = [], []
    while not t.at_end():
        toks = t.next("a frame line").split()
        if version == "v2.1":
            frames.append(t.to_int(toks[0], "frame index"))
            toks = toks[1:]
        else:
            frames.append(len(rows))
        if len(toks) % 3 or (num_verts is not None and len(toks) != 3 * num_verts) or (rows and len(toks) != rows[0].size):
            want = 3 * num_verts if num_verts is not None else (rows[0].size if rows else "a multiple of 3")
            raise t.error(f"expected {want} coordinates, got {len(toks)}")
        try:
            vals = np.array(toks, dtype=np.float32)
        except ValueError:
            vals = np.array(t.floats(toks, "coordinate"), dtype=np.float32)
        if not np.isfinite(vals).all():
            raise t.error("expected finite coordinates, got NaN/inf")
        rows.append(vals)
    if not rows:
        raise DynaCapFormatError(path, 0, "expected at least one frame, got none")
    verts = np.stack(rows).reshape(len(rows), -1, 3)
    return MeshSequence(np.asarray(frames, dtype=np.int64), verts, version)


def write_meshes(path: PathLike, seq: MeshSequence, crlf: bool = False, decimals: int = 1) -> None:
    """Write a v2.1 sequence; DDC writes one decimal (``%.1f``), the default here too.

    Raises:
        ValueError: a vertex that is NaN or inf (nothing is written).
    """
    finite_as(f"{path}: vertices", seq.verts, np.float64)
    out = ["Skeletool Meshes file v2.1 "]
    fmt = f"%.{decimals}f"
    for f, v in zip(seq.frames.tolist(), seq.verts):
        out.append(f"{f} " + " ".join(fmt % x for x in v.ravel().tolist()))
    write_text_atomic(path, "\n".join(out) + "\n", crlf)


