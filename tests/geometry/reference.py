"""Slow loop-based oracles and small test meshes for the geometry tests.

The loops here are deliberate: they restate the definitions texel by texel and face by face so
the vectorised code in ``deliffas.geometry`` can be compared with them on tiny meshes.
Test files load this module by path (``load_reference``) to avoid clashing with other
``reference`` modules of the test tree.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from deliffas.io import cameras
from deliffas.io.cameras import Camera

# ----------------------------------------------------------------------------- meshes and cameras


def icosphere(subdivisions: int = 2, radius: float = 500.0) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def capsule(radius: float, height: float, center=(0.0, 0.0, 0.0), count=(16, 16), max_edge: float = 45.0):
    """A y-aligned capsule (trimesh's is z-aligned) centred at ``center``, its long cylinder
    faces subdivided to edges <= ``max_edge`` (trimesh's capsule has one ring per cap end)."""
    import trimesh

    m = trimesh.creation.capsule(height=height, radius=radius, count=list(count))
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=max_edge)
    v = np.asarray(v, np.float64)[:, [1, 2, 0]] + np.asarray(center)  # cyclic: z -> y, keeps winding
    return v, np.asarray(f, np.int64)


def concat_meshes(*meshes) -> tuple[np.ndarray, np.ndarray]:
    verts, faces, off = [], [], 0
    for v, f in meshes:
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def grid_plane(n: int = 4, size: float = 400.0, z: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An n x n quad grid in the plane z, x and y in [-size/2, size/2], with the affine uv
    u = x / size + 0.5, v = y / size + 0.5 (per-corner: one uv per vertex). Faces face +z."""
    c = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(c, c)
    verts = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, cc, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, cc], 1), np.stack([a, cc, d], 1)])
    uvs = verts[:, :2] / size + 0.5
    return verts, faces, uvs, faces.copy()


def look_at(center, target, width: int, height: int, focal: float, up=(0.0, 1.0, 0.0), name: str = "cam") -> Camera:
    """A pinhole camera at ``center`` looking at ``target`` (image y down = world -up)."""
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return Camera(name, K, cameras.look_at(center, target, up), width, height)


def read_obj_minimal(path: Path):
    """verts, faces, uvs, face_uvs of an OBJ (the project reader when available)."""
    try:
        from deliffas.io.formats.dynacap.character import read_obj

        o = read_obj(path)
        return o.verts, o.faces, o.uvs, o.face_uvs
    except ImportError:
        V, T, F, FT = [], [], [], []
        for line in Path(path).read_text().splitlines():
            p = line.split()
            if not p:
                continue
            if p[0] == "v":
                V.append([float(t) for t in p[1:4]])
            elif p[0] == "vt":
                T.append([float(t) for t in p[1:3]])
            elif p[0] == "f":
                c = [q.split("/") for q in p[1:4]]
                F.append([int(a[0]) - 1 for a in c])
                FT.append([int(a[1]) - 1 for a in c])
        return np.array(V), np.array(F, np.int64), np.array(T), np.array(FT, np.int64)


# ----------------------------------------------------------------------------- oracles


def vertex_normals_loop(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    acc = np.zeros_like(verts, dtype=np.float64)
    for f in faces:
        v0, v1, v2 = verts[f]
        n = np.cross(v1 - v0, v2 - v0)
        for k in f:
            acc[k] += n
    out = np.zeros_like(acc)
    for i in range(len(acc)):
        length = math.sqrt(float(acc[i] @ acc[i]))
        if length > 1e-12:
            out[i] = acc[i] / length
    return out


def _bary_point(p, a, b, c):
    """Barycentrics of 2D point p in triangle (a, b, c), or None for a zero-area triangle."""
    det = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    if abs(det) <= 1e-12:
        return None
    b1 = ((p[0] - a[0]) * (c[1] - a[1]) - (p[1] - a[1]) * (c[0] - a[0])) / det
    b2 = ((b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])) / det
    return np.array([1 - b1 - b2, b1, b2])


def texel_coverage_loop(uvs: np.ndarray, face_uvs: np.ndarray, size: int):
    """Per texel: the set of faces whose UV triangle contains the centre with the best (largest)
    min-barycentric (ties kept), and their barycentrics.

    Returns:
        best: dict (row, col) -> {face: bary}, only for covered texels.
    """
    best = {}
    for i in range(size):
        for j in range(size):
            p = ((j + 0.5) / size, 1.0 - (i + 0.5) / size)
            cands = {}
            for f, fu in enumerate(face_uvs):
                # same texel-index space as the vectorised code: x = u S - 0.5, y = (1 - v) S - 0.5
                tri = [(uvs[k][0] * size - 0.5, (1 - uvs[k][1]) * size - 0.5) for k in fu]
                q = (p[0] * size - 0.5, (1 - p[1]) * size - 0.5)
                b = _bary_point(q, *tri)
                if b is not None and b.min() >= -1e-9:
                    cands[f] = b
            if cands:
                top = max(b.min() for b in cands.values())
                best[(i, j)] = {f: b for f, b in cands.items() if b.min() >= top - 1e-9}
    return best


def gutter_distance_loop(covered: np.ndarray, gutter: int):
    """Per texel filled by ``gutter`` 8-neighbour dilation rings: squared distance to the nearest
    covered texel centre. Returns dict (row, col) -> d2."""
    S = covered.shape[0]
    cov = [(i, j) for i in range(S) for j in range(S) if covered[i, j]]
    out = {}
    for i in range(S):
        for j in range(S):
            if covered[i, j] or not cov:
                continue
            cheb = min(max(abs(i - a), abs(j - b)) for a, b in cov)
            if cheb <= gutter:
                out[(i, j)] = min((i - a) ** 2 + (j - b) ** 2 for a, b in cov)
    return out


def normal_map_loop(vertex_normals: np.ndarray, faces: np.ndarray, face_table: np.ndarray, bary_table: np.ndarray) -> np.ndarray:
    """(3, S, S) normal map, texel by texel."""
    S = face_table.shape[0]
    out = np.zeros((3, S, S))
    for i in range(S):
        for j in range(S):
            f = face_table[i, j]
            if f < 0:
                continue
            n = sum(bary_table[i, j, k] * vertex_normals[faces[f, k]] for k in range(3))
            length = math.sqrt(float(n @ n))
            if length > 1e-8:
                out[:, i, j] = n / length
    return out


def segment_hits_triangle(p, q, a, b, c) -> bool:
    """Möller–Trumbore: does the open segment p -> q cross triangle (a, b, c)?"""
    d = q - p
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = e1 @ h
    if abs(det) < 1e-12:
        return False
    s = p - a
    u = (s @ h) / det
    if u < 0 or u > 1:
        return False
    qq = np.cross(s, e1)
    v = (d @ qq) / det
    if v < 0 or u + v > 1:
        return False
    t = (e2 @ qq) / det
    return 1e-6 < t < 1 - 1e-6
