"""The outer surface: an offset shell of the inner mesh, its safe per-vertex offsets and its checks.

DELIFFAS builds the outer surface by moving every vertex d = 30 mm along its unit vertex normal
(dynacap-formats.md 3.3); faces and per-corner uvs stay those of the inner mesh. Where body parts
are closer than 2 d (armpits, between the legs), and in creases narrower than d, such a shell
crosses itself; ``safe_offsets`` limits d per vertex there, and ``shell_report`` measures what is
left.

Ray casting goes through ``deliffas.geometry.raycast`` (open3d, imported at call time).

Arrays: every function takes numpy arrays or torch tensors. The mesh processing runs in numpy
float64; the per-vertex results (offsets, fold distances, face ids) come back in the kind of
``verts``, in its floating dtype and on its device (``deliffas.geometry.arrays``). ``shell_report``
returns a plain record.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np
import torch
from jaxtyping import Float, Integer, Real

from deliffas.checks import check_shape
from deliffas.io.cameras import Camera
from deliffas.geometry.arrays import ArrayLike, like, to_numpy, to_torch
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.raycast import all_hits, build_scene, first_hits

__all__ = [
    "ShellConfig",
    "ShellReport",
    "offset_shell",
    "safe_offsets",
    "shell_offsets",
    "shell_report",
    "mesh_edges",
    "boundary_edges",
    "self_intersecting_faces",
    "fold_distances",
]

log = logging.getLogger(__name__)

_RAY_START_REL = 1e-5  # rays from a vertex start this far (x bbox diagonal) along the normal
_MAX_RECASTS = 16  # hits in a vertex's own neighbourhood are skipped at most this many times
_SEGMENT_EPS = 1e-6  # self-intersection: segment hits with t in (eps, 1 - eps) count


@dataclass(frozen=True)
class ShellConfig:
    """How the outer surface is built from the inner one."""
    offset_mm: float = 30.0
    """Nominal offset d along the unit vertex normal, mm (DELIFFAS: 30)."""
    safe: bool = False
    """Limit d per vertex where the shell would cross another body part (``safe_offsets``)."""
    min_offset_mm: float = 1.0
    """Safe mode never goes below this offset (a floor; crossings needing less are reported)."""
    safe_fraction: float = 0.45
    """Safe mode: d <= fraction x distance along the normal to the next body part; < 0.5 so two
    facing parts keep a gap of (1 - 2 fraction) x their distance between their shells."""
    neighbourhood_rings: int = 2
    """Safe mode: hits on faces within this many vertex rings of the ray's vertex are ignored."""
    max_slope: float = 0.5
    """Safe mode: d changes by at most this many mm per mm of surface distance around clamps."""
    smooth_iterations: int = 3
    """Safe mode: Laplacian iterations d <- min(d, mean of 1-ring d) before the slope limit."""
    fold_fraction: float | None = None
    """Safe mode, optional: also d <= fold_fraction x the offset at which an incident face of the
    shell would turn inside out (local concave folds; ``fold_distances``). Off by default: the
    repair passes remove folds while clamping fewer vertices."""
    repair_iterations: int = 16
    """Safe mode: passes that shrink the offsets of still-crossing shell faces (0 disables)."""
    repair_shrink: float = 0.8
    """Safe mode: factor applied to those offsets in each repair pass."""


@dataclass
class ShellReport:
    """Validity of an inner mesh and its offset shell (JSON-ready through ``to_dict``).

    Attributes:
        num_verts, num_faces: mesh size.
        watertight: the inner mesh has no boundary and no non-manifold edge.
        num_boundary_edges: edges used by exactly one face.
        boundary_vertex_ids: sorted vertex ids on those edges.
        num_nonmanifold_edges: edges used by more than two faces.
        num_inner_self_intersecting_faces: faces of the inner mesh crossed by a non-adjacent edge.
        num_self_intersecting_faces: same for the outer shell.
        self_intersecting_face_ids: sorted shell face ids involved in a crossing.
        outer_first_fraction: among camera rays hitting the inner surface, the fraction whose
            first outer hit is not behind the inner hit (should be 1.0); None without cameras.
        num_rays_inner: rays hitting the inner surface (over all cameras); None without cameras.
        offset_nominal_mm: the nominal d (max of the offsets when not given); None without offsets.
        num_clamped: vertices whose offset is below nominal; offset_min_mm / offset_mean_mm.
    """
    num_verts: int
    num_faces: int
    watertight: bool
    num_boundary_edges: int
    boundary_vertex_ids: list[int]
    num_nonmanifold_edges: int
    num_inner_self_intersecting_faces: int
    num_self_intersecting_faces: int
    self_intersecting_face_ids: list[int]
    outer_first_fraction: float | None = None
    num_rays_inner: int | None = None
    offset_nominal_mm: float | None = None
    num_clamped: int | None = None
    offset_min_mm: float | None = None
    offset_mean_mm: float | None = None
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """Plain python types only (json.dumps-able)."""
        return asdict(self)


def offset_shell(verts: Float[ArrayLike, "*B V 3"], faces: Integer[ArrayLike, "F 3"],
                 offsets: float | Real[ArrayLike, "... V"]) -> Float[ArrayLike, "*B V 3"]:
    """Outer surface vertices = inner + d * unit vertex normal (same faces, same uvs).

    Args:
        verts: (..., V, 3) float, mm (numpy or torch; the result has the same kind).
        faces: (F, 3) int.
        offsets: scalar d in mm, or per-vertex (V,) / (..., V) offsets in mm.

    Returns:
        (..., V, 3) outer vertices. Vertices without a normal (isolated) stay in place.
    """
    sizes = check_shape("verts", verts, "* V 3")
    normals = vertex_normals(verts, faces)
    if isinstance(verts, torch.Tensor):
        d = to_torch(offsets, verts.dtype, verts.device)
    else:
        d = to_numpy(offsets, np.asarray(verts).dtype)
    if d.ndim:
        check_shape("offsets", d, "* V", sizes)
        d = d[..., None]
    return verts + d * normals


def mesh_edges(faces: Integer[ArrayLike, "F 3"]
               ) -> tuple[Integer[ArrayLike, "E 2"], Integer[ArrayLike, "E"], Integer[ArrayLike, "F 3"]]:
    """Unique undirected edges of a triangle mesh.

    Returns:
        edges (E, 2) int64 sorted pairs, counts (E,) faces per edge, edge_of_corner (F, 3) int64:
        the edge of face f from corner k to corner k + 1; numpy or torch as ``faces``.
    """
    f = to_numpy(faces, np.int64)
    pairs = np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2)  # (3F, 2)
    pairs = np.sort(pairs, axis=1)
    edges, inverse, counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    return like(edges, faces), like(counts, faces), like(inverse.reshape(-1, 3), faces)


def boundary_edges(faces: Integer[ArrayLike, "F 3"]) -> Integer[ArrayLike, "K 2"]:
    """(K, 2) int64 edges used by exactly one face (a hole's rim), numpy or torch as ``faces``."""
    edges, counts, _ = mesh_edges(to_numpy(faces, np.int64))
    return like(edges[counts == 1], faces)


def _bbox_diag(verts: np.ndarray) -> float:
    return float(np.linalg.norm(verts.max(0) - verts.min(0))) if len(verts) else 1.0


def _segment_crosses_triangle(p: np.ndarray, q: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Exact float64 test (N,) bool: the open segment p -> q crosses triangle tri (N, 3, 3) at a
    non-grazing angle (Moller-Trumbore, vectorised). Segments (nearly) parallel to the triangle's
    plane (|sin angle| < 1e-6) do not count."""
    d = q - p
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    det = (e1 * h).sum(1)
    scale = np.linalg.norm(d, axis=1) * np.linalg.norm(np.cross(e1, e2), axis=1)
    ok = np.abs(det) > 1e-6 * np.maximum(scale, 1e-300)
    det = np.where(ok, det, 1.0)
    s = p - tri[:, 0]
    u = (s * h).sum(1) / det
    qq = np.cross(s, e1)
    v = (d * qq).sum(1) / det
    t = (e2 * qq).sum(1) / det
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > _SEGMENT_EPS) & (t < 1 - _SEGMENT_EPS)


def self_intersecting_faces(verts: Real[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"]) -> Integer[ArrayLike, "K"]:
    """Faces crossed by an edge of a non-adjacent face (a vectorised triangle-pair test).

    Two triangles in general position intersect iff an edge of one pierces the other. Every
    unique edge (a, b) is cast as a segment against the whole mesh (open3d
    ``list_intersections``); candidate hits on faces that contain neither a nor b are confirmed
    by an exact float64 segment-triangle test (Embree's float32 reports spurious hits for edges
    lying in a face's plane), and both the hit face and the faces of the edge are reported.
    Coplanar overlaps and crossings between faces sharing a vertex are not detected.

    Args:
        verts: (V, 3) float, mm.
        faces: (F, 3) int.

    Returns:
        (K,) int64 sorted face ids, numpy or torch as ``verts``.
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    return like(_self_intersecting_faces(to_numpy(verts, np.float64), to_numpy(faces, np.int64)), verts)


def _self_intersecting_faces(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    edges, _, edge_of_corner = mesh_edges(faces)
    scene = build_scene(verts, faces)
    a, b = edges[:, 0], edges[:, 1]
    ray_ids, t, face, _ = all_hits(scene, verts[a], verts[b] - verts[a])  # t in segment units
    fv = faces[face]  # (M, 3)
    adjacent = (fv == a[ray_ids, None]).any(1) | (fv == b[ray_ids, None]).any(1)
    cand = np.flatnonzero((t > -1e-3) & (t < 1.0 + 1e-3) & ~adjacent)
    exact = _segment_crosses_triangle(verts[a[ray_ids[cand]]], verts[b[ray_ids[cand]]], verts[fv[cand]])
    crossing = cand[exact]
    bad_edges = np.unique(ray_ids[crossing])
    edge_faces = np.flatnonzero(np.isin(edge_of_corner, bad_edges).any(1))
    return np.union1d(np.unique(face[crossing]), edge_faces).astype(np.int64)


def fold_distances(verts: Real[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"]) -> Float[ArrayLike, "V"]:
    """Per-vertex offset at which the shell first folds locally.

    For a uniform offset d, face f of the shell has normal N(d) = (e1 + d g1) x (e2 + d g2) with
    e the inner edges and g the differences of unit vertex normals; it turns inside out at the
    smallest d > 0 with N(0) . N(d) = 0, a quadratic in d. Convex regions never fold (inf).

    Args:
        verts: (V, 3) float, mm.
        faces: (F, 3) int.

    Returns:
        (V,) min over the incident faces, mm (inf when none folds); numpy or torch as ``verts``, in
        its floating dtype (float64 for integer input).
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    return like(_fold_distances(to_numpy(verts, np.float64), to_numpy(faces, np.int64)), verts)


def _fold_distances(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    normals = vertex_normals(verts, faces)
    p, q = verts[faces], normals[faces]  # (F, 3, 3)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    g1, g2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
    n0 = np.cross(e1, e2)
    a = (n0 * n0).sum(1)  # N0.N(d) = a + b d + c d^2
    b = (n0 * (np.cross(e1, g2) + np.cross(g1, e2))).sum(1)
    c = (n0 * np.cross(g1, g2)).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        quadratic = np.abs(c) > 1e-12 * np.maximum(a, 1e-300)
        disc = b * b - 4 * a * c
        disc = np.where((disc < 0) & (disc > -1e-9 * b * b), 0.0, disc)  # double roots (scaled faces)
        sq = np.sqrt(np.where(quadratic & (disc >= 0), disc, np.nan))
        roots = np.stack([(-b - sq) / (2 * c), (-b + sq) / (2 * c), np.where(quadratic, np.nan, -a / b)], axis=1)
    roots = np.where(roots > 0, roots, np.inf)  # NaN (no real root) compares False
    roots[a <= 0] = np.inf  # degenerate faces carry no information
    per_face = roots.min(1)
    out = np.full(len(verts), np.inf)
    np.minimum.at(out, faces.reshape(-1), np.repeat(per_face, 3))
    return out


def _vertex_face_incidence(faces: np.ndarray, num_verts: int):
    from scipy import sparse

    f = np.asarray(faces, np.int64)
    rows = f.reshape(-1)
    cols = np.repeat(np.arange(len(f)), 3)
    return sparse.csr_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(num_verts, len(f)))


def _neighbourhood_keys(faces: np.ndarray, num_verts: int, rings: int) -> np.ndarray:
    """Sorted keys v * F + f of the faces within ``rings`` vertex rings of each vertex."""
    from scipy import sparse

    inc = _vertex_face_incidence(faces, num_verts).astype(np.int32)  # (V, F)
    adj = ((inc @ inc.T) > 0).astype(np.int32)  # (V, V), 1-ring incl. self
    reach = sparse.identity(num_verts, dtype=np.int32, format="csr")
    for _ in range(max(rings - 1, 0)):  # rings of vertices, not a loop over vertices
        reach = ((reach @ adj) > 0).astype(np.int32)
    near = ((reach @ inc) > 0).tocoo()  # (V, F): faces touching the (rings - 1)-ring vertices
    return np.sort(near.row.astype(np.int64) * len(faces) + near.col.astype(np.int64))


def _distance_to_other_parts(verts: np.ndarray, faces: np.ndarray, normals: np.ndarray, rings: int) -> np.ndarray:
    """Distance (V,) along each vertex normal to the first inner-surface hit outside the vertex's
    own neighbourhood (inf where there is none)."""
    num_verts = len(verts)
    keys = _neighbourhood_keys(faces, num_verts, rings)
    scene = build_scene(verts, faces)
    start = _RAY_START_REL * _bbox_diag(verts)
    dist = np.full(num_verts, np.inf)
    active = np.flatnonzero(np.linalg.norm(normals, axis=1) > 0)
    travelled = np.full(len(active), start)
    for _ in range(_MAX_RECASTS):  # skip own-neighbourhood hits, vectorised over all rays
        if len(active) == 0:
            break
        origins = verts[active] + travelled[:, None] * normals[active]
        t, face, _ = first_hits(scene, origins, normals[active])
        hit = face >= 0
        key = active * len(faces) + np.maximum(face, 0)
        pos = np.minimum(np.searchsorted(keys, key), len(keys) - 1)
        own = hit & (keys[pos] == key)
        done = hit & ~own
        dist[active[done]] = travelled[done] + t[done]
        active, travelled = active[own], travelled[own] + t[own] + start
    return dist


def _lipschitz_envelope(verts: np.ndarray, edges: np.ndarray, d: np.ndarray, slope: float) -> np.ndarray:
    """min_j (d_j + slope * graph distance(i, j)) for every vertex i (Dijkstra from a super-source)."""
    from scipy import sparse
    from scipy.sparse.csgraph import dijkstra

    n = len(d)
    length = np.linalg.norm(verts[edges[:, 0]] - verts[edges[:, 1]], axis=1)
    w = np.maximum(slope * length, 1e-9)  # csgraph treats explicit zeros as missing edges
    shift = 1.0  # source -> j weights d_j + 1 > 0, subtracted again below
    rows = np.concatenate([edges[:, 0], edges[:, 1], np.full(n, n)])
    cols = np.concatenate([edges[:, 1], edges[:, 0], np.arange(n)])
    vals = np.concatenate([w, w, d + shift])
    graph = sparse.csr_matrix((vals, (rows, cols)), shape=(n + 1, n + 1))
    return dijkstra(graph, directed=True, indices=n)[:n] - shift


def _smooth_down(d: np.ndarray, edges: np.ndarray, iterations: int) -> np.ndarray:
    """``iterations`` of d <- min(d, uniform 1-ring mean of d) over the mesh ``edges`` (E, 2)."""
    from scipy import sparse  # the 1-ring mean as one sparse product

    n = len(d)
    adj = sparse.csr_matrix(
        (np.ones(2 * len(edges)), (np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]]))),
        shape=(n, n),
    )
    degree = np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1)
    for _ in range(iterations):  # a few global iterations, each one sparse product
        d = np.minimum(d, (adj @ d) / degree)
    return d


def _repair_crossings(verts: np.ndarray, faces: np.ndarray, normals: np.ndarray, d: np.ndarray,
                      limit: Callable[[np.ndarray], np.ndarray], iterations: int,
                      shrink: float) -> tuple[np.ndarray, int]:
    """Step 5 of :func:`safe_offsets`: shrink the offsets of crossing faces' vertices by ``shrink`` and
    re-``limit`` them (slope limit and floor), at most ``iterations`` times; (offsets, faces still crossing)."""
    num_left = 0
    for _ in range(iterations):  # each pass is one vectorised self-intersection test
        bad = self_intersecting_faces(verts + d[:, None] * normals, faces)
        num_left = len(bad)
        if not num_left:
            break
        ids = np.unique(faces[bad])
        shrunk = d.copy()
        shrunk[ids] *= shrink
        shrunk = limit(shrunk)
        if np.allclose(shrunk, d):
            break  # everything involved already sits on the floor
        d = shrunk
    else:
        num_left = len(self_intersecting_faces(verts + d[:, None] * normals, faces)) if iterations else 0
    return d, num_left


def safe_offsets(
    verts: Real[ArrayLike, "V 3"],
    faces: Integer[ArrayLike, "F 3"],
    offset_mm: float,
    *,
    fraction: float = 0.45,
    min_offset_mm: float = 1.0,
    rings: int = 2,
    max_slope: float = 0.5,
    smooth_iterations: int = 3,
    fold_fraction: float | None = None,
    repair_iterations: int = 16,
    repair_shrink: float = 0.8,
) -> Float[ArrayLike, "V"]:
    """Per-vertex offsets that keep the shell from crossing other body parts and itself.

    1. Cast a ray from each vertex along its unit normal against the inner mesh; skip hits on
       faces within ``rings`` vertex rings of the vertex (its own neighbourhood) and take the
       distance D to the first other hit (inf if none).
    2. d_i = min(offset_mm, fraction * D_i): two facing parts at distance D keep a gap of
       (1 - 2 fraction) D between their shells. With ``fold_fraction``, also
       d_i <= fold_fraction * ``fold_distances`` (local concave folds).
    3. ``smooth_iterations`` of d <- min(d, uniform 1-ring mean of d): smoother, never larger.
    4. Slope limit: d_i = min_j (d_j + max_slope * edge-path length(i, j)) so the offset ramps down
       around a clamp instead of dropping at one vertex (exact, by Dijkstra; applied last so
       the bound holds for the result, floor aside).
    5. Repair: while the shell has self-intersecting faces (``self_intersecting_faces``), multiply
       the offsets of their vertices by ``repair_shrink`` and re-apply the slope limit, at most
       ``repair_iterations`` times. This catches what the normal rays miss: parts approaching
       obliquely (the shells meet off the normals) and creases where the shell folds.
    6. Floor: offsets never go below min(min_offset_mm, offset_mm); crossings that would need
       less are left and counted in a warning (``shell_report`` lists them).

    Args:
        verts: (V, 3) float, mm, the inner mesh.
        faces: (F, 3) int.
        offset_mm: nominal d.

    Returns:
        (V,) offsets in mm, in [floor, offset_mm]; numpy or torch as ``verts``, in its floating dtype
        (float64 for integer input).
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction: expected in (0, 1], got {fraction}")
    if not 0 < repair_shrink < 1:
        raise ValueError(f"repair_shrink: expected in (0, 1), got {repair_shrink}")
    given = verts
    verts = to_numpy(verts, np.float64)
    faces = to_numpy(faces, np.int64)
    floor = min(float(min_offset_mm), float(offset_mm))
    normals = vertex_normals(verts, faces)
    dist = _distance_to_other_parts(verts, faces, normals, rings)
    d = np.minimum(float(offset_mm), fraction * dist)
    if fold_fraction is not None:
        d = np.minimum(d, fold_fraction * fold_distances(verts, faces))
    edges, _, _ = mesh_edges(faces)

    def slope_limit(x: np.ndarray) -> np.ndarray:
        if max_slope is None or max_slope <= 0 or not len(edges):
            return x
        return np.minimum(x, _lipschitz_envelope(verts, edges, x, max_slope))

    if smooth_iterations > 0 and len(edges):
        d = _smooth_down(d, edges, smooth_iterations)
    d = np.maximum(slope_limit(d), floor)
    d, num_left = _repair_crossings(verts, faces, normals, d, lambda x: np.maximum(slope_limit(x), floor),
                                    repair_iterations, repair_shrink)
    if num_left:
        log.warning("safe_offsets: %d shell faces still cross (floor %.3g mm, %d repair passes)", num_left, floor, repair_iterations)
    clamped = d < offset_mm - 1e-9
    if clamped.any():
        log.info("safe_offsets: %d of %d vertices clamped, min %.3g mm", int(clamped.sum()), len(d), float(d.min()))
    return like(d, given)


def shell_offsets(verts: Real[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"], config: ShellConfig) -> Float[ArrayLike, "V"]:
    """(V,) per-vertex offsets in mm for ``config``: constant, or ``safe_offsets`` in safe mode.

    Numpy or torch as ``verts``, in its floating dtype and on its device (float64 for integer input).
    """
    check_shape("verts", verts, "V 3")
    if not config.safe:
        return like(np.full(len(verts), float(config.offset_mm)), verts)
    return safe_offsets(
        verts,
        faces,
        config.offset_mm,
        fraction=config.safe_fraction,
        min_offset_mm=config.min_offset_mm,
        rings=config.neighbourhood_rings,
        max_slope=config.max_slope,
        smooth_iterations=config.smooth_iterations,
        fold_fraction=config.fold_fraction,
        repair_iterations=config.repair_iterations,
        repair_shrink=config.repair_shrink,
    )


def shell_report(
    inner_verts: Real[ArrayLike, "V 3"],
    faces: Integer[ArrayLike, "F 3"],
    outer_verts: Real[ArrayLike, "V 3"],
    cameras: Sequence[Camera] | None = None,
    offsets: Real[ArrayLike, "V"] | None = None,
    *,
    offset_mm: float | None = None,
    depth_tol_mm: float = 1e-3,
) -> ShellReport:
    """Check an inner mesh and its shell.

    Args:
        inner_verts: (V, 3) float, mm.
        faces: (F, 3) int, shared by both surfaces.
        outer_verts: (V, 3) float, mm.
        cameras: optional cameras whose pixel-centre rays test "outer before inner".
        offsets: optional (V,) per-vertex offsets used to build the shell.
        offset_mm: nominal offset for the clamp statistics (default: max of ``offsets``).
        depth_tol_mm: an outer hit up to this far behind the inner hit still counts as first.

    Returns:
        ShellReport.
    """
    sizes = check_shape("inner_verts", inner_verts, "V 3")
    sizes = check_shape("faces", faces, "F 3", sizes)
    check_shape("outer_verts", outer_verts, "V 3", sizes)
    inner = to_numpy(inner_verts, np.float64)
    outer = to_numpy(outer_verts, np.float64)
    faces = to_numpy(faces, np.int64)
    edges, counts, _ = mesh_edges(faces)
    boundary = edges[counts == 1]
    nonmanifold = int((counts > 2).sum())
    inner_bad = self_intersecting_faces(inner, faces)
    outer_bad = self_intersecting_faces(outer, faces)
    if len(boundary) or nonmanifold:
        ids = np.unique(boundary)
        log.warning("shell_report: the inner mesh is not watertight: %d boundary edges at %d vertices (first ids %s), "
                    "%d non-manifold edges; rays through a hole hit the back faces of the far side (the mesh's inside)", len(boundary), len(ids), ids[:10].tolist(), nonmanifold)
    report = ShellReport(
        num_verts=int(sizes["V"]),
        num_faces=int(sizes["F"]),
        watertight=bool(len(boundary) == 0 and nonmanifold == 0),
        num_boundary_edges=int(len(boundary)),
        boundary_vertex_ids=[int(i) for i in np.unique(boundary)],
        num_nonmanifold_edges=nonmanifold,
        num_inner_self_intersecting_faces=int(len(inner_bad)),
        num_self_intersecting_faces=int(len(outer_bad)),
        self_intersecting_face_ids=[int(i) for i in outer_bad],
    )
    if cameras:

        inner_scene, outer_scene = build_scene(inner, faces), build_scene(outer, faces)
        n_inner = n_ok = 0
        for cam in cameras:  # per camera: all its pixels at once
            origins, dirs = cam.rays()
            ti, fi, _ = first_hits(inner_scene, origins, dirs)
            to, _, _ = first_hits(outer_scene, origins, dirs)
            hit = fi >= 0
            n_inner += int(hit.sum())
            n_ok += int((to[hit] <= ti[hit] + depth_tol_mm).sum())
        report.num_rays_inner = n_inner
        report.outer_first_fraction = float(n_ok / n_inner) if n_inner else None
        if not n_inner:
            report.notes.append("no camera ray hits the inner surface")
    if offsets is not None:
        off = to_numpy(offsets, np.float64)
        check_shape("offsets", off, "V", sizes)
        nominal = float(offset_mm) if offset_mm is not None else float(off.max(initial=0.0))
        report.offset_nominal_mm = nominal
        report.num_clamped = int((off < nominal - 1e-6).sum())
        report.offset_min_mm = float(off.min()) if len(off) else None
        report.offset_mean_mm = float(off.mean()) if len(off) else None
    return report
