"""Template variants for the same character: Taubin-smoothed (same topology) and decimated (attributes transferred).

``smooth_variant`` keeps vertex order, faces, UVs, skin and labels and only moves vertices.
``coarse_variant`` decimates with pymeshlab's quadric edge collapse and then transfers every
per-vertex attribute from the dense template: skin weights by barycentric interpolation at the
closest surface point (re-sparsified to <= 6 influences), labels from the nearest vertex, a new
xatlas atlas (``deliffas.geometry.atlas``) and a texture re-baked from the original atlas.

Both return a ``Character`` record; a re-baked texture travels in ``character.extra["texture_png"]``
(PNG bytes) and ``write_variant`` writes the record as a complete DynaCap character folder.

pymeshlab is imported here only, at call time (docs/conventions.md).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np

from deliffas.checks import check_shape
from deliffas.optional import import_optional
from deliffas.io.formats.dynacap.character import Character, ObjData, Skin, write_character
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.atlas import UVAtlas, uv_texel_table

__all__ = [
    "MAX_INFLUENCES",
    "decimate_mesh",
    "remesh_isotropic",
    "taubin_smooth",
    "closest_points_on_mesh",
    "sparsify_weights",
    "smooth_variant",
    "coarse_variant",
    "write_variant",
]

log = logging.getLogger(__name__)

MAX_INFLUENCES = 6
"""Skin influences kept per vertex (the DDC sample always has 6)."""

_CLOSEST_CANDIDATES = 3  # candidate faces per query point (nearest face centroids), besides the nearest vertex's ring
_CHUNK_POINTS = 32768  # query points processed at once by closest_points_on_mesh


def _pymeshlab():
    return import_optional("pymeshlab", "deliffas.geometry.variants needs the 'pymeshlab' package (pip install "
                                        "pymeshlab)")


def _meshset(verts: np.ndarray, faces: np.ndarray):
    pymeshlab = _pymeshlab()
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(verts, dtype=np.float64),
                               face_matrix=np.ascontiguousarray(faces, dtype=np.int32)))
    return ms


def _current(ms) -> tuple[np.ndarray, np.ndarray]:
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), dtype=np.float64), np.asarray(m.face_matrix(), dtype=np.int64)


# --------------------------------------------------------------------------------------------- mesh operations
def decimate_mesh(verts: np.ndarray, faces: np.ndarray, target_faces: int, *, preserve_topology: bool = True,
                  quality_threshold: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Quadric edge-collapse decimation (pymeshlab), keeping boundary and topology.

    Args:
        verts: (V, 3) float, mm.
        faces: (F, 3) int, 0-based, consistently oriented.
        target_faces: wanted face count (pymeshlab stops at or just below it).
        preserve_topology: forbid collapses that change the genus or create non-manifold edges.
        quality_threshold: pymeshlab ``qualitythr``; higher penalises thin triangles more.

    Returns:
        verts (V', 3) float64 and faces (F', 3) int64 of a new mesh (new vertex order).
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    if target_faces < 4:
        raise ValueError(f"target_faces: expected >= 4, got {target_faces}")
    ms = _meshset(verts, faces)
    if target_faces < len(faces):
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=int(target_faces), preservetopology=preserve_topology, preserveboundary=True,
            optimalplacement=True, planarquadric=True, qualitythr=float(quality_threshold), autoclean=True)
    return _current(ms)


def remesh_isotropic(verts: np.ndarray, faces: np.ndarray, target_edge_mm: float,
                     iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic explicit remeshing (pymeshlab) towards edges of ``target_edge_mm``.

    Returns:
        verts (V', 3) float64 and faces (F', 3) int64 of a new mesh.
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    pymeshlab = _pymeshlab()
    ms = _meshset(verts, faces)
    ms.meshing_isotropic_explicit_remeshing(iterations=int(iterations),
                                            targetlen=pymeshlab.PureValue(float(target_edge_mm)),
                                            featuredeg=180.0, checksurfdist=True,
                                            maxsurfdist=pymeshlab.PureValue(0.25 * float(target_edge_mm)))
    return _current(ms)


def _uniform_laplacian(faces: np.ndarray, num_verts: int):
    """Row-normalised adjacency A (V, V) of the mesh edges: (A v)_i = mean of i's neighbours."""
    from scipy import sparse

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    adj = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(num_verts, num_verts))
    deg = np.asarray(adj.sum(axis=1)).ravel()
    inv = sparse.diags(1.0 / np.maximum(deg, 1))
    return (inv @ adj).tocsr(), deg > 0


def taubin_smooth(verts: np.ndarray, faces: np.ndarray, iterations: int, lam: float = 0.5,
                  mu: float = -0.53) -> np.ndarray:
    """Taubin lambda/mu smoothing with the uniform Laplacian (sparse, vectorised; same topology).

    Each iteration applies v += lam (A v - v) then v += mu (A v - v); ``mu < -lam`` undoes the
    shrinkage of the first step, so the volume is nearly preserved.

    Args:
        verts: (V, 3) float, mm.
        faces: (F, 3) int.
        iterations: number of lam/mu pairs (0 returns a copy).

    Returns:
        (V, 3) float64 smoothed vertices in the same order.
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    if iterations < 0:
        raise ValueError(f"iterations: expected >= 0, got {iterations}")
    v = np.array(verts, dtype=np.float64)
    A, has_nbr = _uniform_laplacian(np.asarray(faces, np.int64), len(v))
    mask = has_nbr[:, None].astype(np.float64)  # isolated vertices stay put
    for _ in range(int(iterations)):
        v = v + lam * mask * (A @ v - v)
        v = v + mu * mask * (A @ v - v)
    return v


# --------------------------------------------------------------------------------------------- closest points
def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points to p on triangles (a, b, c), all (..., 3).

    The plane projection is kept when it falls inside the triangle; otherwise the closest point of
    the three edges (segment projections) wins. Degenerate triangles reduce to their edges.

    Returns:
        bary (..., 3) float64 in [0, 1] summing to 1, squared distance (...,).
    """
    dot = lambda x, y: np.einsum("...k,...k->...", x, y)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d00, d01, d11 = dot(ab, ab), dot(ab, ac), dot(ac, ac)
    d20, d21 = dot(ap, ab), dot(ap, ac)
    den = d00 * d11 - d01 * d01
    ok = den > 1e-12 * np.maximum(d00 * d11, 1e-300)
    den = np.where(ok, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    u = 1.0 - v - w
    inside = ok & (u >= 0) & (v >= 0) & (w >= 0)
    q = a + v[..., None] * ab + w[..., None] * ac
    best = np.where(inside, dot(p - q, p - q), np.inf)
    bary = np.stack([u, v, w], axis=-1)
    corners = (a, b, c)
    for i, j in ((0, 1), (1, 2), (2, 0)):  # three edges, vectorised over everything else
        e = corners[j] - corners[i]
        t = np.clip(dot(p - corners[i], e) / np.maximum(dot(e, e), 1e-300), 0.0, 1.0)
        r = p - corners[i] - t[..., None] * e
        d = dot(r, r)
        better = d < best
        best = np.where(better, d, best)
        edge_bary = np.zeros_like(bary)
        edge_bary[..., i] = 1.0 - t
        edge_bary[..., j] = t
        bary = np.where(better[..., None], edge_bary, bary)
    return bary, best


def closest_points_on_mesh(points: np.ndarray, verts: np.ndarray, faces: np.ndarray,
                           candidates: int = _CLOSEST_CANDIDATES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest surface point of a triangle mesh for many query points.

    The exact point-triangle distance is evaluated against the faces around the query's nearest
    vertex plus the ``candidates`` faces whose centroids are nearest (scipy cKDTree); the best of
    those is returned. For query points near the surface (attribute transfer between two versions
    of one template) this is the true closest point except near very long, thin triangles.

    Args:
        points: (N, 3) float, mm.
        verts: (V, 3) float, mm.
        faces: (F, 3) int.

    Returns:
        face (N,) int64, bary (N, 3) float64 (sum 1, in [0, 1]), distance (N,) float64 mm.
    """
    check_shape("points", points, "N 3")
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    V = np.asarray(verts, np.float64)
    Fc = np.asarray(faces, np.int64)
    tri = V[Fc]  # (F, 3, 3)
    k = int(min(candidates, len(Fc)))
    face_tree = cKDTree(tri.mean(axis=1))
    vert_tree = cKDTree(V)
    # vertex -> incident faces as CSR (ring_start, ring_faces)
    order = np.argsort(Fc.ravel(), kind="stable")
    ring_faces = (order // 3).astype(np.int64)
    counts = np.bincount(Fc.ravel(), minlength=len(V))
    ring_start = np.concatenate([[0], np.cumsum(counts)])

    face_out = np.empty(len(pts), np.int64)
    bary_out = np.empty((len(pts), 3))
    dist_out = np.empty(len(pts))
    for start in range(0, len(pts), _CHUNK_POINTS):  # chunks of points, not a per-point loop
        p = pts[start:start + _CHUNK_POINTS]
        n = len(p)
        _, cand = face_tree.query(p, k=k)
        cand = np.asarray(cand).reshape(n, k)
        _, nv = vert_tree.query(p, k=1)
        # flattened (point, face) pairs: the nearest vertex's ring, then the centroid candidates
        c = counts[nv]
        pid_ring = np.repeat(np.arange(n), c)
        pos = np.arange(len(pid_ring)) - np.repeat(np.cumsum(c) - c, c)
        fid_ring = ring_faces[ring_start[nv][pid_ring] + pos]
        pid = np.concatenate([pid_ring, np.repeat(np.arange(n), k)])
        fid = np.concatenate([fid_ring, cand.ravel()])
        t = tri[fid]  # (P, 3, 3)
        b, d2 = _closest_on_triangles(p[pid], t[:, 0], t[:, 1], t[:, 2])
        sel = np.lexsort((d2, pid))  # by point, then distance
        first = np.ones(len(sel), bool)
        first[1:] = pid[sel][1:] != pid[sel][:-1]
        best = sel[first]  # one pair per point, in point order
        face_out[start:start + n] = fid[best]
        bb = b[best]
        bary_out[start:start + n] = bb / bb.sum(-1, keepdims=True)
        dist_out[start:start + n] = np.sqrt(d2[best])
    return face_out, bary_out, dist_out


def sparsify_weights(dense: np.ndarray, max_influences: int = MAX_INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """Keep the largest ``max_influences`` weights per row, by decreasing weight, renormalised to 1.

    Args:
        dense: (V, B) float, non-negative.

    Returns:
        indices (V, K) int64 (-1 padding) and weights (V, K) float64 (0 padding), K = min(B, max).
    """
    check_shape("dense", dense, "V B")
    W = np.clip(np.asarray(dense, np.float64), 0.0, None)
    K = int(min(max_influences, W.shape[1]))
    idx = np.argsort(-W, axis=1, kind="stable")[:, :K]
    w = np.take_along_axis(W, idx, axis=1)
    total = w.sum(axis=1, keepdims=True)
    if (total <= 0).any():
        raise ValueError(f"dense: {int((total <= 0).sum())} rows have no positive weight")
    w = w / total
    idx = np.where(w > 0, idx, -1)
    return idx.astype(np.int64), np.where(idx >= 0, w, 0.0)


# --------------------------------------------------------------------------------------------- variants
def _with_normals(mesh: ObjData, verts: np.ndarray) -> ObjData:

    normals = vertex_normals(verts, mesh.faces) if mesh.normals is not None else None
    fn = mesh.faces.copy() if normals is not None else None
    return dataclasses.replace(mesh, verts=verts, normals=normals, face_normals_idx=fn)


def smooth_variant(character: Character, iterations: int = 10, lam: float = 0.5, mu: float = -0.53) -> Character:
    """The character with a Taubin-smoothed template: same vertex order, faces, UVs, skin, labels,
    graph file and texture; vertex normals are recomputed.

    The rest pose, skeleton and skin are unchanged, so the smoothed template poses exactly like the
    original one (only the rest positions differ).
    """
    verts = taubin_smooth(character.mesh.verts, character.mesh.faces, iterations, lam, mu)
    extra = {**character.extra, "variant": "smooth", "smooth_iterations": int(iterations)}
    return dataclasses.replace(character, mesh=_with_normals(character.mesh, verts), extra=extra)


def _read_texture(character: Character) -> np.ndarray | None:
    """(H, W, 3) float64 RGB in [0, 1] of the character's texture, or None."""
    import cv2

    png = character.extra.get("texture_png")
    if png is not None:
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    elif character.texture is not None and Path(character.texture).is_file():
        img = cv2.imread(str(character.texture), cv2.IMREAD_COLOR)
    else:
        return None
    if img is None:
        raise ValueError(f"{character.path}: cannot decode the texture image")
    return img[..., ::-1].astype(np.float64) / 255.0


def _sample_bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, W, C) image at uv (N, 2) with texel centres at ((j+.5)/W, 1-(i+.5)/H)."""
    H, W = img.shape[:2]
    x = np.clip(uv[:, 0] * W - 0.5, 0, W - 1)
    y = np.clip((1.0 - uv[:, 1]) * H - 0.5, 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2) if W > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2) if H > 1 else np.zeros(len(y), np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 RGB image."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:  # pragma: no cover - cv2 failure
        raise RuntimeError("cv2.imencode failed to encode the texture")
    return buf.tobytes()


def _rebake_texture(src: Character, texture: np.ndarray, verts: np.ndarray, faces: np.ndarray, atlas,
                    size: int) -> np.ndarray:
    """(S, S, 3) uint8 RGB for the new atlas: texel -> 3D point -> closest original point -> its
    original uv -> original texture (bilinear). Texels outside every chart (and its gutter) stay grey."""
    table = uv_texel_table(atlas, size, gutter=4)
    valid = table.valid.ravel()
    face = table.face.ravel()[valid]
    bary = table.bary.reshape(-1, 3)[valid].astype(np.float64)
    pts = (bary[..., None] * verts[faces[face]]).sum(axis=1)
    m = src.mesh
    f_src, b_src, _ = closest_points_on_mesh(pts, m.verts, m.faces)
    uv = (b_src[..., None] * m.uvs[m.face_uvs[f_src]]).sum(axis=1)
    img = np.full((size * size, 3), 0.5)
    img[valid] = _sample_bilinear(texture, uv)
    return np.round(np.clip(img, 0, 1).reshape(size, size, 3) * 255).astype(np.uint8)


def coarse_variant(character: Character, target_faces: int, atlas_res: int = 1024,
                   texture_size: int | None = None) -> Character:
    """The character with a decimated template and every per-vertex attribute transferred.

    * mesh: quadric edge collapse to ``target_faces`` (pymeshlab, topology and boundary kept);
    * skin: dense weights interpolated barycentrically at each new vertex's closest point on the
      original surface, re-sparsified to <= ``MAX_INFLUENCES`` by decreasing weight, rows sum 1;
    * segmentation / hand segmentation: label of the nearest original vertex;
    * UVs: a new xatlas atlas (``UVAtlas.from_mesh``, packing resolution ``atlas_res``);
    * texture: re-baked from the original atlas (``texture_size``, default the original's side;
      carried as PNG bytes in ``extra["texture_png"]``);
    * graph: the original ``*_graph.obj`` is reused (it is bound to the new template when posed);
      when it has more than half as many nodes as the new template has vertices it is decimated
      to about a sixth of them instead.

    Returns:
        A Character record (nominal paths of the original); write it with ``write_variant``.
    """
    from scipy.spatial import cKDTree

    mesh = character.mesh
    verts, faces = decimate_mesh(mesh.verts, mesh.faces, target_faces)
    f_src, b_src, _ = closest_points_on_mesh(verts, mesh.verts, mesh.faces)
    corners = mesh.faces[f_src]  # (V', 3)
    dense = character.skin.dense()
    W = (b_src[..., None] * dense[corners]).sum(axis=1)  # (V', Bn)
    idx, w = sparsify_weights(W)
    skin = Skin(character.skin.bones, idx, w)
    _, nearest = cKDTree(mesh.verts).query(verts, k=1)
    seg = character.segmentation[nearest] if character.segmentation is not None else None
    hseg = character.hand_segmentation[nearest] if character.hand_segmentation is not None else None
    colors = (b_src[..., None] * mesh.colors[corners]).sum(axis=1) if mesh.colors is not None else None
    atlas = UVAtlas.from_mesh(verts, faces, resolution=atlas_res, padding=4)
    extra = {k: v for k, v in character.extra.items() if k != "texture_png"}
    extra.update(variant="coarse", target_faces=int(target_faces))
    texture = _read_texture(character)
    if texture is not None:
        if not mesh.has_uvs:
            log.warning("coarse_variant: %s has a texture but no uvs; the texture is not re-baked", character.path)
        else:
            size = int(texture_size or texture.shape[0])
            extra["texture_png"] = _encode_png(_rebake_texture(character, texture, verts, faces, atlas, size))
    graph = character.graph
    if graph is not None and graph.num_verts > len(verts) // 2:
        gv, gf = decimate_mesh(graph.verts, graph.faces, max(2 * (len(verts) // 6), 8))
        log.warning("coarse_variant: the graph's %d nodes exceed half the %d new vertices; decimated to %d nodes",
                    graph.num_verts, len(verts), len(gv))
        graph = ObjData(gv, gf)
    new_mesh = ObjData(verts, faces, np.asarray(atlas.uvs).copy(), np.asarray(atlas.face_uvs).copy(), colors,
                       None if mesh.normals is None else np.zeros((0, 3)), None, mesh.mtllib, mesh.material)
    new_mesh = _with_normals(new_mesh, verts)
    return dataclasses.replace(character, mesh=new_mesh, skin=skin, segmentation=seg, hand_segmentation=hseg,
                               graph=graph, texture=None if "texture_png" in extra else character.texture,
                               extra=extra)


def write_variant(directory: str | os.PathLike, character: Character, name: str, crlf: bool = False) -> Path:
    """Write a variant (or any Character record) as a complete DynaCap character folder.

    The texture is ``extra["texture_png"]`` when present, else the file ``character.texture``.

    Returns:
        Path of ``<directory>/<name>.character``.
    """
    return write_character(directory, character, name, crlf=crlf, texture_png=character.extra.get("texture_png"))
