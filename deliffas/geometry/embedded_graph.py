"""The DDC embedded deformation graph: C++-faithful binding and batched torch deformation (formats doc 1.7, 2.2).

Binding (``bind_embedded_graph``): each graph vertex, in file order, takes the nearest not yet used
template vertex; node radii and vertex weights come from breadth-first hop distances over the
template edges. Deformation (``EmbeddedDeformation``):

    canonical  v̂_i = Σ_k w_ik [R(α_k)(v_i − g_k) + g_k + Δt_k] + d_i,   R = R_z(γ) R_y(β) R_x(α)
    posed      v'_i = Σ_k w_ik [R_sk,k v̂_i + t_sk,k]

where (R_sk,k, t_sk,k) is the dual-quaternion blend of the bone transforms with the skin weights of
node k's template vertex (``blend_bone_transforms``). With zero parameters this is node-resampled
skinning, not per-vertex skinning (formats doc 2.2).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from jaxtyping import Float, Integer
import torch
from torch import nn

from deliffas.checks import check_shape
from deliffas.io.obj import ObjData
from deliffas.geometry.skinning import quaternion_to_matrix, rigid_to_dual_quaternion

__all__ = [
    "EmbeddedGraph",
    "bind_embedded_graph",
    "rigidity_of_labels",
    "euler_to_matrix",
    "blend_bone_transforms",
    "embedded_canonical",
    "EmbeddedDeformation",
    "MIN_NODE_RADIUS",
]

log = logging.getLogger(__name__)

MIN_NODE_RADIUS = 3
"""Node radii (in hops) are clamped from below at this value (C++ ``EmbeddedGraph.cpp``)."""
_NEAREST_CANDIDATES = 32  # template vertices examined per node before a full search
_BFS_CHUNK = 256  # nodes whose hop distances are held at once ((chunk, V) floats)
_HOP_LIMIT = 16  # BFS depth per node; deeper searches only where a graph neighbour lies farther

_RIGIDITY = {0: 10.0, 5: 10.0, 6: 10.0, 7: 10.0, 10: 10.0, 12: 10.0, 9: 15.0, 8: 50.0, 11: 50.0,
             **{k: 200.0 for k in (1, 2, 3, 4, 13, 14, 15, 16, 17, 18, 19)}}
"""Segmentation label -> EG rigidity weight (C++ ``trimesh.cpp``, formats doc 1.8 use 1)."""


@dataclass(frozen=True)
class EmbeddedGraph:
    """A graph bound to a template.

    Attributes:
        node_verts: (K,) int64 template vertex of each node (graph file order).
        node_positions: (K, 3) float64 g_k = rest position of that template vertex, mm.
        node_radius: (K,) int64 radius r_k in hops (>= MIN_NODE_RADIUS).
        edges: (E, 2) int64 node-node connections (edges of the graph triangles), i < j.
        vertex_nodes: (V, M) int64 nodes influencing each template vertex, by decreasing weight;
            -1 pads.
        vertex_weights: (V, M) float64 matching weights (0 pads), rows sum to 1.
        rigidity: (K,) float64 mean segmentation rigidity of the vertices attached to each node,
            or None without a segmentation.
        num_unattached: template vertices within no node radius (given the hop-nearest node).
    """

    node_verts: Integer[np.ndarray, "K"]
    node_positions: Float[np.ndarray, "K 3"]
    node_radius: Integer[np.ndarray, "K"]
    edges: Integer[np.ndarray, "E 2"]
    vertex_nodes: Integer[np.ndarray, "V M"]
    vertex_weights: Float[np.ndarray, "V M"]
    rigidity: Float[np.ndarray, "K"] | None = None
    num_unattached: int = 0

    @property
    def num_nodes(self) -> int:
        return int(self.node_verts.shape[0])

    @property
    def num_verts(self) -> int:
        return int(self.vertex_nodes.shape[0])

    def dense_weights(self) -> np.ndarray:
        """(V, K) float64 dense weight matrix."""
        W = np.zeros((self.num_verts, self.num_nodes))
        rows = np.repeat(np.arange(self.num_verts), self.vertex_nodes.shape[1])
        idx = self.vertex_nodes.ravel()
        keep = idx >= 0
        np.add.at(W, (rows[keep], idx[keep]), self.vertex_weights.ravel()[keep])
        return W


def rigidity_of_labels(labels: np.ndarray) -> np.ndarray:
    """(V,) float64 EG rigidity weight per vertex from LIP segmentation labels.

    Raises:
        ValueError: for a label outside 0..19 (the C++ tool would loop forever on it).
    """
    labels = np.asarray(labels, np.int64)
    lut = np.full(20, np.nan)
    for k, v in _RIGIDITY.items():
        lut[k] = v
    bad = (labels < 0) | (labels > 19)
    if bad.any():
        raise ValueError(f"segmentation: labels must be 0..19 (LIP), got {sorted(set(labels[bad].tolist()))[:5]}")
    return lut[labels]


def _mesh_adjacency(faces: np.ndarray, num_verts: int):
    from scipy import sparse

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    adj = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(num_verts, num_verts))
    adj.data[:] = 1.0
    return adj


def _graph_edges(graph_faces: np.ndarray) -> np.ndarray:
    e = np.concatenate([graph_faces[:, [0, 1]], graph_faces[:, [1, 2]], graph_faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0).astype(np.int64)


def _greedy_nearest_unused(verts: np.ndarray, points: np.ndarray) -> np.ndarray:
    """For each point in order, the nearest template vertex not taken by an earlier point."""
    from scipy.spatial import cKDTree

    if len(points) > len(verts):
        raise ValueError(f"graph has {len(points)} nodes but the template only {len(verts)} vertices")
    k = int(min(_NEAREST_CANDIDATES, len(verts)))
    _, cand = cKDTree(verts).query(points, k=k)
    cand = np.asarray(cand).reshape(len(points), k)
    used = np.zeros(len(verts), bool)
    out = np.empty(len(points), np.int64)
    for n in range(len(points)):  # sequential by definition (C++ order); one small check per node
        free = cand[n][~used[cand[n]]]
        if len(free):
            pick = int(free[0])
        else:  # all candidates taken: search every unused vertex
            rest = np.flatnonzero(~used)
            pick = int(rest[np.argmin(((verts[rest] - points[n]) ** 2).sum(1))])
        used[pick] = True
        out[n] = pick
    return out


def _neighbour_lists(edges: np.ndarray, K: int) -> np.ndarray:
    """(K, maxdeg) int64 graph neighbours of each node, -1 padding."""
    both = np.concatenate([edges, edges[:, ::-1]])
    order = np.lexsort((both[:, 1], both[:, 0]))
    both = both[order]
    deg = np.bincount(both[:, 0], minlength=K)
    nbr = np.full((K, max(int(deg.max(initial=0)), 1)), -1, np.int64)
    starts = np.concatenate([[0], np.cumsum(deg)[:-1]])
    nbr[both[:, 0], np.arange(len(both)) - starts[both[:, 0]]] = both[:, 1]
    return nbr


def _attach_by_hops(adj, node_verts: np.ndarray, nbr: np.ndarray,
                    V: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 2-3 of :func:`bind_embedded_graph` by batched breadth-first searches over the template edges.

    Returns:
        radius (K,) hops; the attachments as node ids, vertex ids and weights (each (A,)); and each vertex's
        hop-nearest node (V,).
    """
    from scipy.sparse.csgraph import dijkstra  # scipy's graph search, only when a graph is bound

    K = len(node_verts)
    radius = np.empty(K, np.int64)
    rows_k, rows_i, rows_w = [], [], []
    best_hops = np.full(V, np.inf)
    best_node = np.zeros(V, np.int64)
    for start in range(0, K, _BFS_CHUNK):  # chunks of nodes; each chunk one batched BFS
        ks = np.arange(start, min(start + _BFS_CHUNK, K))
        # depth-limited BFS; exact for nodes whose graph neighbours lie within the limit, since then
        # r_k <= limit / 2 (the limit is at least MIN_NODE_RADIUS for nodes without neighbours)
        D = dijkstra(adj, unweighted=True, indices=node_verts[ks], limit=max(_HOP_LIMIT, MIN_NODE_RADIUS))  # (c, V)
        nb = nbr[ks]
        nb_hops = np.where(nb >= 0, D[np.arange(len(ks))[:, None], node_verts[np.maximum(nb, 0)]], -np.inf)
        beyond = np.nonzero(np.isposinf(nb_hops).any(axis=1))[0]
        if len(beyond):  # a graph neighbour farther than the limit: redo those rows without it
            D[beyond] = dijkstra(adj, unweighted=True, indices=node_verts[ks[beyond]])
            nb_hops[beyond] = np.where(nb[beyond] >= 0, D[beyond[:, None], node_verts[np.maximum(nb[beyond], 0)]],
                                       -np.inf)
        far = nb_hops.max(axis=1)
        far = np.where(np.isfinite(far), far, 0)
        r = np.maximum(MIN_NODE_RADIUS, (far // 2).astype(np.int64))
        radius[ks] = r
        d = D / r[:, None]
        kk, ii = np.nonzero(d <= 1.0)
        rows_k.append(ks[kk])
        rows_i.append(ii)
        rows_w.append(np.exp(-0.5 * d[kk, ii] ** 2))
        chunk_best = np.argmin(D, axis=0)
        chunk_hops = D[chunk_best, np.arange(V)]
        better = chunk_hops < best_hops
        best_hops[better] = chunk_hops[better]
        best_node[better] = ks[chunk_best[better]]
    far_verts = np.flatnonzero(np.isinf(best_hops))
    if len(far_verts):  # farther than the hop limit from every node: search from those vertices instead
        Dv = dijkstra(adj, unweighted=True, indices=far_verts)[:, node_verts]  # (n, K)
        best_node[far_verts] = np.argmin(Dv, axis=1)
    return radius, np.concatenate(rows_k), np.concatenate(rows_i), np.concatenate(rows_w), best_node


def _node_rigidity(segmentation: np.ndarray, refinement: bool, kk: np.ndarray, ii: np.ndarray, V: int,
                   K: int) -> np.ndarray:
    """(K,) mean ``rigidity_of_labels`` of the vertices attached to each node (step 4)."""
    rho_v = rigidity_of_labels(np.asarray(segmentation))
    if len(rho_v) != V:
        raise ValueError(f"segmentation: expected {V} labels, got {len(rho_v)}")
    if refinement:
        rho_v = np.where(rho_v < 20, rho_v / 10.0, rho_v)
    sums = np.bincount(kk, weights=rho_v[ii], minlength=K)
    counts = np.bincount(kk, minlength=K)
    return sums / np.maximum(counts, 1)


def _vertex_rows(kk: np.ndarray, ii: np.ndarray, ww: np.ndarray, V: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex rows sorted by decreasing weight, padded to the largest attachment count: node ids (V, M),
    -1 padding, and weights (V, M) normalised per vertex."""
    order = np.lexsort((-ww, ii))
    kk, ii, ww = kk[order], ii[order], ww[order]
    counts = np.bincount(ii, minlength=V)
    M = int(counts.max())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(ii)) - starts[ii]
    vertex_nodes = np.full((V, M), -1, np.int64)
    vertex_weights = np.zeros((V, M))
    vertex_nodes[ii, slot] = kk
    vertex_weights[ii, slot] = ww
    vertex_weights /= vertex_weights.sum(axis=1, keepdims=True)
    return vertex_nodes, vertex_weights


def bind_embedded_graph(verts: np.ndarray, faces: np.ndarray, graph: ObjData | np.ndarray,
                        segmentation: np.ndarray | None = None, graph_faces: np.ndarray | None = None,
                        refinement: bool = False) -> EmbeddedGraph:
    """Bind an embedded graph to a template as the C++ tool does (formats doc 1.7).

    1. Nodes: graph vertices in file order, each the nearest unused template vertex.
    2. Radius r_k = max(MIN_NODE_RADIUS, max hops to the graph neighbours' vertices // 2), hops =
       breadth-first distance over the template edges (scipy.sparse.csgraph).
    3. Vertex i attaches to node k when d = hops(i, k) / r_k <= 1, with w = exp(-d^2 / 2),
       normalised per vertex; a vertex attached to nothing takes its hop-nearest node (w = 1).
    4. Rigidity ρ_k = mean ``rigidity_of_labels`` over the vertices attached to k (with
       ``refinement``, values below 20 are divided by 10 first, as the C++ option).

    The C++ restriction to the same connected component (for multi-component templates) is not
    reproduced: hop distances across components are infinite, so such vertices simply do not
    attach there.

    Args:
        verts: (V, 3) float, template rest vertices, mm.
        faces: (F, 3) int template faces.
        graph: the ``*_graph.obj`` (its vertices and triangles), or (K, 3) node positions with
            ``graph_faces``.
        segmentation: optional (V,) LIP labels for the node rigidity.
        graph_faces: (G, 3) int graph triangles when ``graph`` is an array.

    Returns:
        EmbeddedGraph.
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    verts = np.asarray(verts, np.float64)
    faces = np.asarray(faces, np.int64)
    if isinstance(graph, ObjData):
        gpos, gfaces = graph.verts, graph.faces
    else:
        if graph_faces is None:
            raise ValueError("bind_embedded_graph: give graph_faces with an array of node positions")
        gpos, gfaces = np.asarray(graph, np.float64), np.asarray(graph_faces, np.int64)
    check_shape("graph vertices", gpos, "K 3")
    V, K = len(verts), len(gpos)
    node_verts = _greedy_nearest_unused(verts, gpos)
    edges = _graph_edges(gfaces)
    nbr = _neighbour_lists(edges, K)
    radius, kk, ii, ww, best_node = _attach_by_hops(_mesh_adjacency(faces, V), node_verts, nbr, V)
    attached = np.zeros(V, bool)
    attached[ii] = True
    lone = np.flatnonzero(~attached)
    if len(lone):
        log.info("bind_embedded_graph: %d vertices within no node radius take their hop-nearest node", len(lone))
    rigidity = _node_rigidity(segmentation, refinement, kk, ii, V, K) if segmentation is not None else None
    kk = np.concatenate([kk, best_node[lone]])
    ii = np.concatenate([ii, lone])
    ww = np.concatenate([ww, np.ones(len(lone))])
    vertex_nodes, vertex_weights = _vertex_rows(kk, ii, ww, V)
    return EmbeddedGraph(node_verts, verts[node_verts].copy(), radius, edges, vertex_nodes, vertex_weights,
                         rigidity, int(len(lone)))


# --------------------------------------------------------------------------------------------- torch maths
def euler_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """R = R_z(γ) · R_y(β) · R_x(α) for angles (..., 3) = (α, β, γ) about x, y, z (radians).

    Returns:
        (..., 3, 3).
    """
    a, b, c = angles.unbind(-1)
    ca, sa, cb, sb, cc, sc = torch.cos(a), torch.sin(a), torch.cos(b), torch.sin(b), torch.cos(c), torch.sin(c)
    return torch.stack([
        cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa,
        sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa,
        -sb, cb * sa, cb * ca,
    ], dim=-1).reshape(*angles.shape[:-1], 3, 3)


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def blend_bone_transforms(indices: torch.Tensor, weights: torch.Tensor, bone_transforms: torch.Tensor,
                          mode: Literal["dqs", "lbs"] = "dqs") -> tuple[torch.Tensor, torch.Tensor]:
    """Per-item blended transforms of the bones (the node transforms of formats doc 2.2 step 1).

    ``dqs`` follows the C++ reference exactly like ``deliffas.geometry.skinning.dqs``: influences
    after the first are negated when their real part's dot product with the first's is negative,
    the blend is divided by the norm of its real part. ``lbs`` sums the 3x4 matrices (not rigid).

    Args:
        indices: (N, K) long bone indices, -1 = padding.
        weights: (N, K) weights (0 for padding).
        bone_transforms: (B, Bn, 4, 4) per-bone transforms relative to the rest pose.

    Returns:
        rotations (B, N, 3, 3) and translations (B, N, 3), so x' = R x + t.
    """
    check_shape("indices", indices, "N K")
    check_shape("weights", weights, "N K", {"N": indices.shape[0], "K": indices.shape[1]})
    check_shape("bone_transforms", bone_transforms, "B Bn 4 4")
    idx = indices.clamp(min=0)
    w = weights * (indices >= 0)
    if mode == "lbs":
        M = (w[None, :, :, None, None] * bone_transforms[:, idx, :3, :]).sum(2)  # (B, N, 3, 4)
        return M[..., :3], M[..., 3]
    if mode != "dqs":
        raise ValueError(f"mode must be 'dqs' or 'lbs', got {mode!r}")
    real, dual = rigid_to_dual_quaternion(bone_transforms)  # (B, Bn, 4)
    r, d = real[:, idx], dual[:, idx]  # (B, N, K, 4)
    sign = torch.where((r * r[:, :, :1]).sum(-1) < 0, -1.0, 1.0).to(r.dtype)
    ws = (w * sign).unsqueeze(-1)
    br, bd = (ws * r).sum(2), (ws * d).sum(2)
    norm = br.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    br, bd = br / norm, bd / norm
    conj = br * torch.tensor([1, -1, -1, -1], dtype=br.dtype, device=br.device)
    return quaternion_to_matrix(br), 2 * _quat_mul(bd, conj)[..., 1:]


def embedded_canonical(rest_verts: torch.Tensor, node_positions: torch.Tensor, vertex_nodes: torch.Tensor,
                       vertex_weights: torch.Tensor, node_rotations: torch.Tensor | None,
                       node_translations: torch.Tensor | None, vertex_deltas: torch.Tensor | None) -> torch.Tensor:
    """v̂_i = Σ_k w_ik [R_k (v_i − g_k) + g_k + Δt_k] + d_i (the rest-pose non-rigid deformation).

    Args:
        rest_verts: (V, 3) mm.
        node_positions: (K, 3) g_k, mm.
        vertex_nodes: (V, M) long, -1 pads; vertex_weights: (V, M), rows sum to 1.
        node_rotations: (B, K, 3, 3) or None (identity).
        node_translations: (B, K, 3) mm or None (zero).
        vertex_deltas: (B, V, 3) mm or None (zero).

    Returns:
        (B, V, 3) canonical vertices; B = 1 when every parameter is None.
    """
    B = next((x.shape[0] for x in (node_rotations, node_translations, vertex_deltas) if x is not None), 1)
    out = rest_verts.expand(B, -1, -1)
    idx = vertex_nodes.clamp(min=0)
    w = (vertex_weights * (vertex_nodes >= 0)).unsqueeze(-1)  # (V, M, 1)
    if node_rotations is not None:
        g = node_positions[idx]  # (V, M, 3)
        local = rest_verts[:, None, :] - g
        rotated = torch.einsum("bvmij,vmj->bvmi", node_rotations[:, idx], local) + g  # (B, V, M, 3)
        out = (w * rotated).sum(2)
    if node_translations is not None:
        out = out + (w * node_translations[:, idx]).sum(2)
    if vertex_deltas is not None:
        out = out + vertex_deltas
    return out


class EmbeddedDeformation(nn.Module):
    """The bound graph as buffers plus the canonical deformation and the node-interpolated posing.

    Args:
        graph: the binding from ``bind_embedded_graph``.
        rest_verts: (V, 3) template rest vertices, mm.
        dtype: buffer dtype.
    """

    def __init__(self, graph: EmbeddedGraph, rest_verts: np.ndarray, dtype: torch.dtype = torch.float32):
        super().__init__()
        check_shape("rest_verts", rest_verts, "V 3", {"V": graph.num_verts})
        self.register_buffer("rest_verts", torch.tensor(np.asarray(rest_verts), dtype=dtype))
        self.register_buffer("node_verts", torch.as_tensor(graph.node_verts, dtype=torch.long))
        self.register_buffer("node_positions", torch.tensor(graph.node_positions, dtype=dtype))
        self.register_buffer("vertex_nodes", torch.as_tensor(graph.vertex_nodes, dtype=torch.long))
        self.register_buffer("vertex_weights", torch.tensor(graph.vertex_weights, dtype=dtype))
        self.register_buffer("edges", torch.as_tensor(graph.edges, dtype=torch.long))
        rho = graph.rigidity if graph.rigidity is not None else np.ones(graph.num_nodes)
        self.register_buffer("rigidity", torch.tensor(rho, dtype=dtype))

    @property
    def num_nodes(self) -> int:
        return int(self.node_verts.shape[0])

    def canonical(self, node_angles: torch.Tensor | None = None, node_translations: torch.Tensor | None = None,
                  vertex_deltas: torch.Tensor | None = None) -> torch.Tensor:
        """(B, V, 3) canonical vertices from node Euler angles (B, K, 3) rad, node translations
        (B, K, 3) mm and per-vertex deltas (B, V, 3) mm (each optional)."""
        K, V = self.num_nodes, self.rest_verts.shape[0]
        sizes: dict[str, int] = {"K": K, "V": V}
        for name, x, spec in (("node_angles", node_angles, "B K 3"), ("node_translations", node_translations, "B K 3"),
                              ("vertex_deltas", vertex_deltas, "B V 3")):
            if x is not None:
                sizes = check_shape(name, x, spec, sizes)
        R = euler_to_matrix(node_angles.to(self.rest_verts)) if node_angles is not None else None
        t = node_translations.to(self.rest_verts) if node_translations is not None else None
        d = vertex_deltas.to(self.rest_verts) if vertex_deltas is not None else None
        return embedded_canonical(self.rest_verts, self.node_positions, self.vertex_nodes, self.vertex_weights, R, t, d)

    def pose(self, canonical: torch.Tensor, node_rotations: torch.Tensor,
             node_translations: torch.Tensor) -> torch.Tensor:
        """v'_i = Σ_k w_ik [R_k v̂_i + t_k] for skinned node transforms R (B, K, 3, 3), t (B, K, 3).

        ``canonical`` (B or 1, V, 3). Returns (B, V, 3).
        """
        idx = self.vertex_nodes.clamp(min=0)
        w = self.vertex_weights * (self.vertex_nodes >= 0)  # (V, M)
        A = torch.einsum("vm,bvmij->bvij", w, node_rotations[:, idx])  # (B, V, 3, 3)
        b = torch.einsum("vm,bvmi->bvi", w, node_translations[:, idx])
        return torch.einsum("bvij,bvj->bvi", A, canonical.expand(A.shape[0], -1, -1)) + b

    def deformed_nodes(self, node_rotations: torch.Tensor, node_translations: torch.Tensor,
                       node_offsets: torch.Tensor | None = None) -> torch.Tensor:
        """Posed node positions R_sk,k (g_k + Δt_k) + t_sk,k, (B, K, 3) mm."""
        g = self.node_positions if node_offsets is None else self.node_positions + node_offsets
        return torch.einsum("bkij,...kj->bki", node_rotations, g) + node_translations
