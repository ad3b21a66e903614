"""Readers and writers of the Skeletool/DynaCap files (dynacap-formats.md section 1) as typed records.

Every reader is strict: a file that does not match its format raises ``DynaCapFormatError`` naming
the file, the line and what was expected. Every writer produces files its reader reads back
identically (within the printed precision); ``crlf=True`` writes the CRLF line ends that the original
C++ tools need on Linux.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from jaxtyping import Float, Integer

from deliffas.io.obj import ObjData, read_obj, write_obj
from deliffas.io.motion import Motion
from deliffas.io.formats.dynacap.skeleton import Skeleton, read_skeleton, write_skeleton
from deliffas.io.infra.text_lines import DynaCapFormatError, TextLines, read_text, write_text_atomic

__all__ = [
    "DynaCapFormatError",
    "read_motion", "write_motion",
    "Skin", "read_skin", "write_skin",
    "Character", "CharacterFiles", "read_character", "write_character", "read_character_files",
    "read_segmentation", "write_segmentation",
    "ObjData", "read_obj", "write_obj", "read_graph",
]

PathLike = str | os.PathLike

MOTION_HEADERS = ("Skeletool Motion File V1.0", "Skeletool Motion File V0.1")
SKIN_HEADER = "Skeletool character skinning file V1.0"
SKIN_WEIGHT_SUM_TOLERANCE = 1e-3
"""How far a vertex's skin weights may sum from 1 (the DDC sample: within 2e-6 after un-gluing)."""
CHARACTER_HEADERS = ("skeletool character file v1.0", "skeletool character file v0.3", "skeletool character file v0.1")


# --------------------------------------------------------------------------------------------- motion
def read_motion(path: PathLike, num_dofs: int | None = None) -> Motion:
    """Read a ``.motion`` file; ``num_dofs`` (the skeleton's) is checked on every line when given.

    V0.1 files are converted to V1.0 semantics (DOFs with index > 2 change sign, as the C++ reader).
    """
    text = read_text(path, "motion file")
    first = text.lstrip().split("\n", 1)[0].strip()
    if first.startswith("HIERARCHY"):
        raise DynaCapFormatError(path, 1, "BVH motion files are not supported; convert to Skeletool motion V1.0")
    t = TextLines(path, text)
    header = t.header(MOTION_HEADERS)
    frames, rows = [], []
    width = num_dofs
    while not t.at_end():
        toks = t.next("a motion line 'frame dof...'").split()
        if width is None:
            width = len(toks) - 1
            if width < 1:
                raise t.error("expected a frame index followed by DOF values, got a single token")
        if len(toks) != width + 1:
            raise t.error(f"expected frame index + {width} DOF values, got {len(toks) - 1} values")
        frames.append(t.to_int(toks[0], "frame index"))
        try:
            vals = np.array(toks[1:], dtype=np.float64)
        except ValueError:
            vals = np.array(t.floats(toks[1:], "DOF value"))
        if not np.isfinite(vals).all():
            raise t.error(f"expected finite DOF values, got NaN/inf in column {int(np.argmin(np.isfinite(vals)))}")
        rows.append(vals)
    if not rows:
        raise DynaCapFormatError(path, 2, "expected at least one motion line, got none")
    dofs = np.stack(rows)
    if header.endswith("V0.1"):
        dofs[:, 3:] *= -1
    return Motion(np.asarray(frames, dtype=np.int64), dofs)


def write_motion(path: PathLike, motion: Motion, crlf: bool = False, precision: int = 10) -> None:
    """Write a V1.0 motion. ``precision`` significant digits (the C++ writer uses 6; we keep more)."""
    lines = [MOTION_HEADERS[0]]
    fmt = f"%{precision + 5}.{precision}g"
    for f, row in zip(motion.frames.tolist(), motion.dofs):
        lines.append(f"{f:>4} " + " ".join(fmt % v for v in row))
    write_text_atomic(path, "\n".join(lines) + "\n", crlf)


# --------------------------------------------------------------------------------------------- skin
@dataclass(frozen=True)
class Skin:
    """Skinning weights: per vertex up to K (bone index, weight) influences, by decreasing weight.

    Attributes:
        bones: the B bone names of the file (a bone resolves to a joint by name, formats doc 1.5).
        indices: (V, K) int64 bone indices, -1 for padding.
        weights: (V, K) float64 weights, 0 for padding.
    """

    bones: tuple[str, ...]
    indices: Integer[np.ndarray, "V K"]
    weights: Float[np.ndarray, "V K"]

    @property
    def num_verts(self) -> int:
        return int(self.indices.shape[0])

    def dense(self) -> Float[np.ndarray, "V B"]:
        """(V, B) float64 dense weight matrix."""
        W = np.zeros((self.num_verts, len(self.bones)))
        rows = np.repeat(np.arange(self.num_verts), self.indices.shape[1])
        idx, w = self.indices.ravel(), self.weights.ravel()
        keep = idx >= 0
        np.add.at(W, (rows[keep], idx[keep]), w[keep])
        return W


def _unglue_weight(token: str, vertex_token: str) -> str | None:
    """The weight token with the glued vertex index removed, or None when it does not end with it."""
    if token.endswith(vertex_token) and len(token) > len(vertex_token):
        return token[: -len(vertex_token)]
    return None


def read_skin(path: PathLike, num_verts: int | None = None) -> Skin:
    """Read a ``.skin`` file, decoding the glued weight/vertex-index tokens of the DDC samples.

    In the sample files every weight but the last on a line is followed without a space by the
    vertex index (formats doc 1.5). The file is decoded as glued when every multi-influence line
    shows that pattern, otherwise as well-separated tokens (what our writer and the C++ writer emit).
    """
    t = TextLines(path, what="skin file")
    t.header((SKIN_HEADER,))
    if t.next("'bones:'") != "bones:":
        raise t.error("expected 'bones:'")
    bones = tuple(t.next("the bone names").split())
    if t.next("'vertex weights:'") != "vertex weights:":
        raise t.error("expected 'vertex weights:'")
    lines: list[tuple[int, list[str]]] = []
    while not t.at_end():
        toks = t.next("a vertex weight line").split()
        lines.append((t.line_no, toks))
    if not lines:
        raise DynaCapFormatError(path, 0, "expected vertex weight lines, got none")
    glued_votes = [
        all(_unglue_weight(tok, toks[0]) is not None for tok in toks[2:-2:2])
        for _, toks in lines
        if len(toks) >= 5 and len(toks) % 2 == 1
    ]
    glued = bool(glued_votes) and sum(glued_votes) > 0.9 * len(glued_votes)
    K = max((len(toks) - 1) // 2 for _, toks in lines)
    V = len(lines)
    indices = np.full((V, K), -1, dtype=np.int64)
    weights = np.zeros((V, K))
    for row, (line_no, toks) in enumerate(lines):
        err = lambda msg: DynaCapFormatError(path, line_no, msg)  # noqa: E731
        if len(toks) < 3 or len(toks) % 2 == 0:
            raise err(f"expected vertex index followed by (bone index, weight) pairs, got {len(toks)} tokens")
        try:
            vid = int(toks[0])
        except ValueError:
            raise err(f"expected an integer vertex index, got '{toks[0][:30]}'") from None
        if vid != row:
            raise err(f"expected vertex index {row} (lines in vertex order), got {vid}")
        pairs = toks[1:]
        for k in range(len(pairs) // 2):
            b_tok, w_tok = pairs[2 * k], pairs[2 * k + 1]
            if glued and k < len(pairs) // 2 - 1:
                stripped = _unglue_weight(w_tok, toks[0])
                if stripped is None:
                    raise err(f"expected weight {k} to end with the glued vertex index {toks[0]}, got '{w_tok[:30]}'")
                w_tok = stripped
            try:
                b = int(b_tok)
                w = float(w_tok)
            except ValueError:
                raise err(f"expected (bone index, weight) pair, got '{b_tok[:20]} {w_tok[:20]}'") from None
            if not 0 <= b < len(bones):
                raise err(f"bone index {b} out of range 0..{len(bones) - 1}")
            if not np.isfinite(w):
                raise err("expected a finite weight, got NaN/inf")
            if w < 0:
                raise err(f"expected a weight >= 0, got {w!r} (bone {b})")
            indices[row, k], weights[row, k] = b, w
        total = float(weights[row].sum())
        if abs(total - 1.0) > SKIN_WEIGHT_SUM_TOLERANCE:
            raise err(f"expected the vertex's weights to sum to 1 (within {SKIN_WEIGHT_SUM_TOLERANCE}), got {total:.6g}")
    if num_verts is not None and V != num_verts:
        raise DynaCapFormatError(path, lines[-1][0], f"expected {num_verts} vertex lines (mesh vertices), got {V}")
    return Skin(bones, indices, weights)


def write_skin(path: PathLike, skin: Skin, crlf: bool = False) -> None:
    """Write a ``.skin`` file with well-separated tokens (never the glued form)."""
    out = [SKIN_HEADER, "bones:", "   " + " ".join(skin.bones), "vertex weights:"]
    for v in range(skin.num_verts):
        keep = skin.indices[v] >= 0
        pairs = " ".join(f"{b} {w!r}" for b, w in zip(skin.indices[v][keep].tolist(), skin.weights[v][keep].tolist()))
        out.append(f"{v} {pairs}")
    write_text_atomic(path, "\n".join(out) + "\n", crlf)


# --------------------------------------------------------------------------------------------- segmentation
def read_segmentation(path: PathLike, num_verts: int | None = None) -> Integer[np.ndarray, "V"]:
    """(V,) int64 per-vertex labels, one integer per line in vertex order (formats doc 1.8)."""
    t = TextLines(path, what="segmentation file")
    labels = []
    while not t.at_end():
        toks = t.tokens("one integer label", 1)
        labels.append(t.to_int(toks[0], "label"))
    if num_verts is not None and len(labels) != num_verts:
        raise DynaCapFormatError(path, t.line_no, f"expected {num_verts} labels (one per vertex), got {len(labels)}")
    return np.asarray(labels, dtype=np.int64)


def write_segmentation(path: PathLike, labels: Integer[np.ndarray, "V"], crlf: bool = False) -> None:
    write_text_atomic(path, "\n".join(str(int(x)) for x in labels) + "\n", crlf)


# --------------------------------------------------------------------------------------------- character
@dataclass(frozen=True)
class CharacterFiles:
    """The paths a ``.character`` file names (absolute, resolved against its directory)."""

    skeleton: Path
    mesh: Path
    skin: Path
    pose: Path | None
    dof_file: Path | None = None


@dataclass(frozen=True)
class Character:
    """A DynaCap character: skeleton, template mesh (in the rest pose), skin, rest pose and extras.

    Attributes:
        path: the ``.character`` file.
        files: the files it names.
        skeleton: joints, DOFs and scaling groups (``deliffas.io.formats.dynacap.skeleton``).
        mesh: the template mesh in the rest pose: ``mesh.verts`` (V, 3) float64 mm, ``mesh.faces``
            (F, 3) int64, ``mesh.uvs`` (T, 2) float64 and ``mesh.face_uvs`` (F, 3) int64 per-corner
            uv indices (see :class:`~deliffas.io.obj.ObjData`). Its ``v`` order is the vertex order
            everywhere.
        skin: per-vertex bone influences, (V, K) indices and weights.
        rest_dofs: (D,) float64 DOF values of the rest pose, DOF units (frame 0 of the ``pose``
            motion; zeros when the character names none).
        segmentation: (V,) int64 labels from ``segmentation.txt`` next to the mesh, or None.
        hand_segmentation: (V,) int64 from ``hand_segmentation.txt``, or None.
        graph: the embedded graph ``<mesh stem>_graph.obj`` next to the mesh (its vertices are
            graph nodes, mm), or None.
        texture: path of the texture image (``map_Kd`` of the mesh's material), or None.
        extra: anything else a reader keeps, not compared by ``==``.
    """

    path: Path
    files: CharacterFiles
    skeleton: Skeleton
    mesh: ObjData
    skin: Skin
    rest_dofs: Float[np.ndarray, "D"]
    segmentation: Integer[np.ndarray, "V"] | None = None
    hand_segmentation: Integer[np.ndarray, "V"] | None = None
    graph: ObjData | None = None
    texture: Path | None = None
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def directory(self) -> Path:
        return self.path.parent


def read_character_files(path: PathLike) -> CharacterFiles:
    """Parse only the ``.character`` file (paths relative to its directory)."""
    p = Path(path)
    t = TextLines(p, what="character file")
    header = t.header(CHARACTER_HEADERS)
    entries: dict[str, list[Path]] = {}
    while not t.at_end():
        key = t.next("a keyword (skeleton, mesh, skin, pose)")
        if key not in ("skeleton", "mesh", "skin", "pose"):
            raise t.error(f"expected a keyword skeleton, mesh, skin or pose, got '{key[:40]}'")
        n_paths = 2 if key == "skeleton" and not header.endswith("v1.0") else 1
        entries[key] = [p.parent / t.next(f"the path after '{key}'") for _ in range(n_paths)]
    for key in ("skeleton", "mesh", "skin"):
        if key not in entries:
            raise DynaCapFormatError(p, 0, f"expected a '{key}' entry, found none")
    for key, paths in entries.items():
        for q in paths:
            try:
                exists = q.is_file()
            except OSError as err:  # e.g. a path longer than the file system allows
                raise DynaCapFormatError(p, 0, f"'{key}' path is not a usable file name ({err.strerror})") from None
            if not exists:
                raise DynaCapFormatError(p, 0, f"'{key}' file {str(q)[:200]} referenced by the character does not exist")
    sk = entries["skeleton"]
    return CharacterFiles(sk[0], entries["mesh"][0], entries["skin"][0],
                          entries["pose"][0] if "pose" in entries else None, sk[1] if len(sk) > 1 else None)


def _texture_path(mesh_path: Path, obj: ObjData) -> Path | None:
    if not obj.mtllib:
        return None
    mtl = mesh_path.parent / obj.mtllib
    if not mtl.is_file():
        return None
    for line in read_text(mtl, "material file").splitlines():
        toks = line.split()
        if toks and toks[0] == "map_Kd" and len(toks) > 1:
            tex = mtl.parent / toks[-1]
            return tex if tex.is_file() else None
    return None


def read_character(path: PathLike) -> Character:
    """Read a ``.character`` and everything it references, checking the files agree with each other."""
    files = read_character_files(path)
    skel = read_skeleton(files.skeleton)
    mesh = read_obj(files.mesh)
    skin = read_skin(files.skin, num_verts=mesh.num_verts)
    for name in skin.bones:
        if not any(j.name.startswith(name) for j in skel.joints):
            raise DynaCapFormatError(files.skin, 3, f"bone '{name}' matches no joint of {files.skeleton.name}")
    if files.pose is not None:
        pose = read_motion(files.pose, num_dofs=skel.num_dofs)
        rest = pose.dofs[pose.row_of(0)] if 0 in pose.frames else pose.dofs[0]
    else:
        rest = np.zeros(skel.num_dofs)
    mesh_dir = files.mesh.parent
    seg = mesh_dir / "segmentation.txt"
    hseg = mesh_dir / "hand_segmentation.txt"
    graph = mesh_dir / f"{files.mesh.stem}_graph.obj"
    return Character(
        path=Path(path),
        files=files,
        skeleton=skel,
        mesh=mesh,
        skin=skin,
        rest_dofs=np.asarray(rest, dtype=np.float64),
        segmentation=read_segmentation(seg, mesh.num_verts) if seg.is_file() else None,
        hand_segmentation=read_segmentation(hseg, mesh.num_verts) if hseg.is_file() else None,
        graph=read_graph(graph) if graph.is_file() else None,
        texture=_texture_path(files.mesh, mesh),
    )


def read_graph(path: PathLike) -> ObjData:
    """Read an embedded graph ``*_graph.obj`` (its vertices are the graph nodes, formats doc 1.7)."""
    return read_obj(path)


def write_character(directory: PathLike, character: Character, name: str = "character", crlf: bool = False,
                    texture_png: bytes | None = None) -> Path:
    """Write ``character`` as a complete DynaCap character folder and return the ``.character`` path.

    Writes ``<name>.character``, ``.skeleton``, ``.obj`` (+ ``.obj.mtl`` and the texture when known),
    ``.skin``, ``.motion`` (the rest pose, frame 0), ``segmentation.txt``, ``hand_segmentation.txt``
    and ``<name>_graph.obj`` when present. ``texture_png`` overrides the texture bytes.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    tex_bytes = texture_png
    if tex_bytes is None and character.texture is not None and Path(character.texture).is_file():
        tex_bytes = Path(character.texture).read_bytes()
    write_skeleton(d / f"{name}.skeleton", character.skeleton, crlf)
    mesh = character.mesh
    if tex_bytes is not None:
        (d / f"{name}.png").write_bytes(tex_bytes)
        write_text_atomic(d / f"{name}.obj.mtl", f"newmtl material_0\nKa 0.2 0.2 0.2\nKd 1 1 1\nillum 1\nmap_Kd {name}.png\n", crlf)
        mesh = ObjData(mesh.verts, mesh.faces, mesh.uvs, mesh.face_uvs, mesh.colors, mesh.normals,
                       mesh.face_normals_idx, f"./{name}.obj.mtl", "material_0")
    else:
        mesh = ObjData(mesh.verts, mesh.faces, mesh.uvs, mesh.face_uvs, mesh.colors, mesh.normals,
                       mesh.face_normals_idx, None, None)
    write_obj(d / f"{name}.obj", mesh, crlf)
    write_skin(d / f"{name}.skin", character.skin, crlf)
    write_motion(d / f"{name}.motion", Motion(np.zeros(1, dtype=np.int64), character.rest_dofs[None]), crlf)
    if character.segmentation is not None:
        write_segmentation(d / "segmentation.txt", character.segmentation, crlf)
    if character.hand_segmentation is not None:
        write_segmentation(d / "hand_segmentation.txt", character.hand_segmentation, crlf)
    if character.graph is not None:
        write_obj(d / f"{name}_graph.obj", character.graph, crlf)
    text = (f"skeletool character file v1.0\nskeleton\n  {name}.skeleton\nmesh\n  {name}.obj\n"
            f"skin\n  {name}.skin\npose\n  {name}.motion\n")
    write_text_atomic(d / f"{name}.character", text, crlf)
    return d / f"{name}.character"
