"""Embedded graph: C++-faithful binding (against a loop/BFS reference), deformation maths and posing modes."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
import torch

from deliffas.io.obj import ObjData
from deliffas.geometry.embedded_graph import (MIN_NODE_RADIUS, EmbeddedDeformation, bind_embedded_graph,
                                              blend_bone_transforms, euler_to_matrix, rigidity_of_labels)
from deliffas.geometry.skeleton import axis_angle_to_matrix
from deliffas.geometry.templates import DDCTemplate, EmbeddedGraphTemplate


def _bfs(neighbours: list[list[int]], src: int) -> np.ndarray:
    hops = np.full(len(neighbours), np.inf)
    hops[src] = 0
    q = deque([src])
    while q:
        u = q.popleft()
        for w in neighbours[u]:
            if hops[w] == np.inf:
                hops[w] = hops[u] + 1
                q.append(w)
    return hops


def _reference_binding(verts, faces, gverts, gfaces):
    """Slow loop reference of formats doc 1.7 (nearest unused vertex, BFS hops, radii, weights)."""
    used, node_verts = set(), []
    for p in gverts:
        order = np.argsort(((verts - p) ** 2).sum(1), kind="stable")
        pick = next(int(i) for i in order if int(i) not in used)
        used.add(pick)
        node_verts.append(pick)
    nbrs = [set() for _ in range(len(verts))]
    for a, b, c in faces:
        for u, w in ((a, b), (b, c), (c, a)):
            nbrs[u].add(int(w))
            nbrs[w].add(int(u))
    nbrs = [sorted(n) for n in nbrs]
    gn = [set() for _ in range(len(gverts))]
    for a, b, c in gfaces:
        for u, w in ((a, b), (b, c), (c, a)):
            gn[u].add(int(w))
            gn[w].add(int(u))
    hops = np.stack([_bfs(nbrs, v) for v in node_verts])
    radius = np.array([max(MIN_NODE_RADIUS, int(max(hops[k, node_verts[j]] for j in gn[k])) // 2)
                       for k in range(len(gverts))])
    W = np.zeros((len(verts), len(gverts)))
    for k in range(len(gverts)):
        for i in range(len(verts)):
            d = hops[k, i] / radius[k]
            if d <= 1:
                W[i, k] = np.exp(-d * d / 2)
    for i in np.nonzero(W.sum(1) == 0)[0]:
        W[i, int(np.argmin(hops[:, i]))] = 1.0
    return np.array(node_verts), radius, W / W.sum(1, keepdims=True)


@pytest.fixture(scope="module")
def small_mesh():
    import trimesh

    fine = trimesh.creation.icosphere(subdivisions=3, radius=100.0)
    coarse = trimesh.creation.icosphere(subdivisions=1, radius=101.0)
    return (np.asarray(fine.vertices), np.asarray(fine.faces, np.int64),
            np.asarray(coarse.vertices), np.asarray(coarse.faces, np.int64))


def test_binding_matches_loop_reference(small_mesh):
    verts, faces, gv, gf = small_mesh
    eg = bind_embedded_graph(verts, faces, ObjData(gv, gf))
    node_verts, radius, W = _reference_binding(verts, faces, gv, gf)
    np.testing.assert_array_equal(eg.node_verts, node_verts)
    np.testing.assert_array_equal(eg.node_radius, radius)
    np.testing.assert_allclose(eg.dense_weights(), W, atol=1e-12)
    np.testing.assert_allclose(eg.node_positions, verts[node_verts])
    assert (np.diff(eg.vertex_weights, axis=1) <= 1e-15).all(), "per-vertex weights by decreasing weight"


def test_unattached_vertices_take_hop_nearest_node(small_mesh):
    verts, faces, gv, gf = small_mesh
    nodes = verts[faces[0]]  # three adjacent vertices: radius 3 hops covers a small patch only
    eg = bind_embedded_graph(verts, faces, nodes, graph_faces=np.array([[0, 1, 2]]))
    W = eg.dense_weights()
    np.testing.assert_allclose(W.sum(1), 1.0)
    assert (eg.node_radius == MIN_NODE_RADIUS).all() and eg.num_unattached > 500
    _, _, ref = _reference_binding(verts, faces, nodes, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(W, ref, atol=1e-12)


def test_depth_limited_bfs_falls_back_exactly(small_mesh, monkeypatch):
    """With a tiny BFS depth limit every fallback path runs; the binding must not change."""
    import deliffas.geometry.embedded_graph as eg_module

    verts, faces, gv, gf = small_mesh
    ref = bind_embedded_graph(verts, faces, ObjData(gv, gf))
    lone_ref = bind_embedded_graph(verts, faces, verts[faces[0]], graph_faces=np.array([[0, 1, 2]]))
    monkeypatch.setattr(eg_module, "_HOP_LIMIT", 1)
    limited = bind_embedded_graph(verts, faces, ObjData(gv, gf))
    lone = bind_embedded_graph(verts, faces, verts[faces[0]], graph_faces=np.array([[0, 1, 2]]))
    for a, b in ((ref, limited), (lone_ref, lone)):
        np.testing.assert_array_equal(a.node_radius, b.node_radius)
        np.testing.assert_array_equal(a.vertex_nodes, b.vertex_nodes)
        np.testing.assert_allclose(a.vertex_weights, b.vertex_weights)


def test_rigidity_labels():
    np.testing.assert_array_equal(rigidity_of_labels(np.array([0, 5, 12, 9, 8, 11, 13, 18])),
                                  [10, 10, 10, 15, 50, 50, 200, 200])
    with pytest.raises(ValueError, match="0..19"):
        rigidity_of_labels(np.array([0, 20]))


def test_euler_convention():
    ang = torch.tensor([[0.3, -0.7, 1.1]], dtype=torch.float64)
    ex, ey, ez = torch.eye(3, dtype=torch.float64)
    Rx = axis_angle_to_matrix(ex, ang[0, 0])
    Ry = axis_angle_to_matrix(ey, ang[0, 1])
    Rz = axis_angle_to_matrix(ez, ang[0, 2])
    torch.testing.assert_close(euler_to_matrix(ang)[0], Rz @ Ry @ Rx)


@pytest.fixture(scope="module")
def sample_graph(sample_character):
    c = sample_character
    return bind_embedded_graph(c.mesh.verts, c.mesh.faces, c.graph, c.segmentation)


def test_sample_binding(sample_character, sample_graph):
    g, c = sample_graph, sample_character
    assert g.num_nodes == 852 and g.num_verts == 5514
    assert len(np.unique(g.node_verts)) == 852
    d0 = np.linalg.norm(c.mesh.verts - c.graph.verts[0], axis=1)
    assert g.node_verts[0] == np.argmin(d0), "the first node takes the nearest template vertex"
    assert (g.node_radius >= MIN_NODE_RADIUS).all()
    np.testing.assert_allclose(g.vertex_weights.sum(1), 1.0, atol=1e-12)
    assert g.rigidity is not None and ((g.rigidity >= 10) & (g.rigidity <= 200)).all()
    assert len(g.edges) == 2550, "852 nodes, 1700 triangles, genus 0: E = 3F/2"


def test_zero_parameters_reproduce_skinning(sample_character, sample_graph, sample_motion):
    c = sample_character
    x = torch.tensor(sample_motion.dofs[[0, 500, 999]])
    base = DDCTemplate(c, dtype=torch.float64)
    per_vertex = EmbeddedGraphTemplate(c, sample_graph, deformation="per_vertex", dtype=torch.float64)
    zeros = dict(node_angles=torch.zeros(3, 852, 3, dtype=torch.float64),
                 node_translations=torch.zeros(3, 852, 3, dtype=torch.float64),
                 vertex_deltas=torch.zeros(3, 5514, 3, dtype=torch.float64))
    torch.testing.assert_close(per_vertex.pose(x, **zeros), base.pose(x), atol=1e-9, rtol=0)
    torch.testing.assert_close(per_vertex.pose(x, skinning="lbs"), base.pose(x, skinning="lbs"), atol=1e-9, rtol=0)
    eg = per_vertex.pose(x, deformation="embedded_graph", **zeros)
    d = (eg - base.pose(x)).norm(dim=-1)
    assert d.median() < 3.0 and d.max() < 60.0, "node-resampled skinning stays close to per-vertex skinning"
    assert d.max() > 1e-3, "but it is a different model"
    rest = torch.tensor(c.rest_dofs)[None]
    torch.testing.assert_close(per_vertex.pose(rest, deformation="embedded_graph")[0],
                               torch.tensor(c.mesh.verts), atol=1e-8, rtol=0)


def test_node_translation_moves_only_nearby_vertices(sample_character, sample_graph):
    c = sample_character
    t = EmbeddedGraphTemplate(c, sample_graph, dtype=torch.float64)
    k = 400
    dt = torch.zeros(1, 852, 3, dtype=torch.float64)
    dt[0, k] = torch.tensor([0.0, 0.0, 20.0])
    rest = torch.tensor(c.rest_dofs)[None]
    moved = (t.pose(rest, node_translations=dt) - t.pose(rest))[0].norm(dim=-1).numpy()
    w = sample_graph.dense_weights()[:, k]
    assert (moved[w == 0] < 1e-9).all(), "vertices outside the node's radius do not move"
    np.testing.assert_allclose(moved[w > 0], 20.0 * w[w > 0], rtol=1e-6, atol=1e-9)
    hops_far = np.linalg.norm(c.mesh.verts[w > 0] - sample_graph.node_positions[k], axis=1)
    assert hops_far.max() < 150, "only a local patch"


def test_node_rotation_about_its_own_position(sample_character, sample_graph):
    c = sample_character
    defm = EmbeddedDeformation(sample_graph, c.mesh.verts, torch.float64)
    ang = torch.zeros(1, 852, 3, dtype=torch.float64)
    ang[:, :, 1] = 0.3  # every node rotates by the same angle: a rigid rotation about each node
    out = defm.canonical(node_angles=ang)[0].numpy()
    nodes_moved = out[sample_graph.node_verts] - c.mesh.verts[sample_graph.node_verts]
    assert np.isfinite(out).all() and np.abs(out - c.mesh.verts).max() > 1.0
    # a vertex bound to a single node rotates about that node's position
    single = np.nonzero((sample_graph.vertex_nodes[:, 1] < 0))[0]
    if len(single):
        i = single[0]
        k = sample_graph.vertex_nodes[i, 0]
        R = euler_to_matrix(ang[0, k]).numpy()
        g = sample_graph.node_positions[k]
        np.testing.assert_allclose(out[i], R @ (c.mesh.verts[i] - g) + g, atol=1e-9)
    assert np.abs(nodes_moved).max() < np.abs(out - c.mesh.verts).max() + 1e-9


def test_blend_dqs_is_rigid_and_checks_mode(unchecked):
    rng = np.random.default_rng(0)
    T = torch.eye(4, dtype=torch.float64).repeat(1, 4, 1, 1)
    axes = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(1, 4, 3))), dim=-1)
    T[..., :3, :3] = axis_angle_to_matrix(axes, torch.tensor(rng.uniform(-2, 2, size=(1, 4))))
    T[..., :3, 3] = torch.tensor(rng.normal(size=(1, 4, 3)) * 100)
    idx = torch.tensor([[0, 1, 2], [3, 1, -1]])
    w = torch.tensor([[0.5, 0.3, 0.2], [0.7, 0.3, 0.0]], dtype=torch.float64)
    Rb, tb = blend_bone_transforms(idx, w, T)
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(Rb @ Rb.transpose(-1, -2), eye.expand_as(Rb), atol=1e-12, rtol=0)
    assert torch.allclose(torch.linalg.det(Rb), torch.ones(1, 2, dtype=torch.float64))
    one = blend_bone_transforms(torch.tensor([[2]]), torch.tensor([[1.0]], dtype=torch.float64), T)
    torch.testing.assert_close(one[0][0, 0], T[0, 2, :3, :3])
    torch.testing.assert_close(one[1][0, 0], T[0, 2, :3, 3])
    with unchecked(), pytest.raises(ValueError, match="mode"):
        blend_bone_transforms(idx, w, T, mode="slerp")
