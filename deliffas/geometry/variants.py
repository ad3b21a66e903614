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
from deliffas.data.dynacap import Character, ObjData, Skin, write_character

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

_CLOSEST_CANDIDATES = 16  # candidate faces per query point (nearest face centroids)
_CHUNK_POINTS = 65536  # query points processed at once by closest_points_on_mesh


def _pymeshlab():
    try:
        import pymeshlab
    except ImportError as exc:  # pragma: no cover - hard dependency
        raise ImportError("deliffas.geometry.variants needs the 'pymeshlab' package (pip install pymeshlab)") from exc
    return pymeshlab


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
def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentrics (..., 3) of the closest point to p on triangles (a, b, c) (Ericson, vectorised).

    All inputs (..., 3). Degenerate triangles fall back to their closest vertex or edge.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1 = (ab * ap).sum(-1)
    d2 = (ac * ap).sum(-1)
    bp = p - b
    d3 = (ab * bp).sum(-1)
    d4 = (ac * bp).sum(-1)
    cp = p - c
    d5 = (ab * cp).sum(-1)
    d6 = (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    eps = 1e-30
    # interior
    denom = va + vb + vc
    denom = np.where(np.abs(denom) < eps, eps, denom)
    v = vb / denom
    w = vc / denom
    out = np.stack([1 - v - w, v, w], -1)

    def put(mask, bary):
        nonlocal out
        out = np.where(mask[..., None], bary, out)

    zeros = np.zeros_like(d1)
    ones = np.ones_like(d1)
    # edge BC
    t_bc = (d4 - d3) / np.where(np.abs((d4 - d3) + (d5 - d6)) < eps, eps, (d4 - d3) + (d5 - d6))
    put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([zeros, 1 - t_bc, t_bc], -1))
    # edge AC
    t_ac = d2 / np.where(np.abs(d2 - d6) < eps, eps, d2 - d6)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - t_ac, zeros, t_ac], -1))
    # edge AB
    t_ab = d1 / np.where(np.abs(d1 - d3) < eps, eps, d1 - d3)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - t_ab, t_ab, zeros], -1))
    # vertex regions
    put((d6 >= 0) & (d5 <= d6), np.stack([zeros, zeros, ones], -1))
    put((d3 >= 0) & (d4 <= d3), np.stack([zeros, ones, zeros], -1))
    put((d1 <= 0) & (d2 <= 0), np.stack([ones, zeros, zeros], -1))
    return np.clip(out, 0.0, 1.0)


def closest_points_on_mesh(points: np.ndarray, verts: np.ndarray, faces: np.ndarray,
                           candidates: int = _CLOSEST_CANDIDATES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest surface point of a triangle mesh for many query points.

    The exact point-triangle distance is evaluated against the ``candidates`` faces whose centroids
    are nearest to the query (scipy cKDTree) plus every face around the nearest vertex; the best
    of those is returned. For query points near the surface (attribute transfer between two
    versions of one template) this is the true closest point.

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
    # faces around each vertex, padded to the max valence (CSR of the vertex-face incidence)
    inc_v = Fc.ravel()
    inc_f = np.repeat(np.arange(len(Fc)), 3)
    order = np.argsort(inc_v, kind="stable")
    inc_v, inc_f = inc_v[order], inc_f[order]
    counts = np.bincount(inc_v, minlength=len(V))
    valence = int(counts.max(initial=1))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ring = np.full((len(V), valence), -1, np.int64)
    slot = np.arange(len(inc_v)) - starts[inc_v]
    ring[inc_v, slot] = inc_f
    ring = np.where(ring < 0, ring[:, :1], ring)  # pad with a valid repeat

    face_out = np.empty(len(pts), np.int64)
    bary_out = np.empty((len(pts), 3))
    dist_out = np.empty(len(pts))
    for start in range(0, len(pts), _CHUNK_POINTS):  # chunks of points, not a per-point loop
        p = pts[start:start + _CHUNK_POINTS]
        _, cand = face_tree.query(p, k=k)
        cand = np.asarray(cand).reshape(len(p), k)
        _, nv = vert_tree.query(p, k=1)
        cand = np.concatenate([cand, ring[nv]], axis=1)  # (n, k + valence)
        t = tri[cand]  # (n, c, 3, 3)
        pp = np.broadcast_to(p[:, None, :], t.shape[:2] + (3,))
        b = _closest_on_triangles(pp, t[..., 0, :], t[..., 1, :], t[..., 2, :])  # (n, c, 3)
        q = (b[..., None] * t).sum(-2)
        d = np.linalg.norm(q - p[:, None, :], axis=-1)
        best = np.argmin(d, axis=1)
        rows = np.arange(len(p))
        face_out[start:start + len(p)] = cand[rows, best]
        bb = b[rows, best]
        bary_out[start:start + len(p)] = bb / bb.sum(-1, keepdims=True)
        dist_out[start:start + len(p)] = d[rows, best]
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
