"""Template variants: Taubin smoothing keeps everything but positions; decimation transfers every attribute."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.io.formats.dynacap.character import read_character
from deliffas.geometry.variants import (_closest_on_triangles, _sample_bilinear, closest_points_on_mesh,
                                        coarse_variant, smooth_variant, sparsify_weights, taubin_smooth,
                                        write_variant)
from deliffas.geometry.templates import DDCTemplate

@pytest.fixture(scope="module")
def character(procedural_character_path):
    return read_character(procedural_character_path)


@pytest.fixture(scope="module")
def coarse(character):
    return coarse_variant(character, 3000, atlas_res=256)


def _volume(v, f):
    t = v[f]
    return np.einsum("fi,fi->f", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6


def test_taubin_matches_dense_reference():
    rng = np.random.default_rng(0)
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    v = np.asarray(m.vertices) + rng.normal(0, 1.0, (len(m.vertices), 3))
    f = np.asarray(m.faces)
    A = np.zeros((len(v), len(v)))
    for a, b, c in f:  # dense uniform adjacency, loop reference
        for i, j in ((a, b), (b, c), (c, a)):
            A[i, j] = A[j, i] = 1
    A /= A.sum(1, keepdims=True)
    ref = v.copy()
    for _ in range(3):
        ref = ref + 0.5 * (A @ ref - ref)
        ref = ref - 0.53 * (A @ ref - ref)
    np.testing.assert_allclose(taubin_smooth(v, f, 3), ref, atol=1e-10)


def test_smooth_keeps_topology_uvs_skin(character, tmp_path):
    s = smooth_variant(character, 10)
    m0, m1 = character.mesh, s.mesh
    np.testing.assert_array_equal(m1.faces, m0.faces)
    np.testing.assert_array_equal(m1.uvs, m0.uvs)
    np.testing.assert_array_equal(m1.face_uvs, m0.face_uvs)
    assert s.skin is character.skin and s.segmentation is character.segmentation and s.graph is character.graph
    moved = np.linalg.norm(m1.verts - m0.verts, axis=1)
    assert moved.max() > 0.5 and moved.mean() < 5.0
    shrink = 1 - _volume(m1.verts, m1.faces) / _volume(m0.verts, m0.faces)
    assert abs(shrink) < 0.02, "Taubin lambda/mu hardly shrinks"
    # smoother: the mean umbrella-Laplacian length drops
    def roughness(v):
        from deliffas.geometry.variants import _uniform_laplacian

        A, _ = _uniform_laplacian(m0.faces, len(v))
        return np.linalg.norm(A @ v - v, axis=1).mean()
    assert roughness(m1.verts) < 0.8 * roughness(m0.verts)
    path = write_variant(tmp_path / "smooth", s, "smooth")
    back = read_character(path)
    np.testing.assert_allclose(back.mesh.verts, m1.verts, atol=1e-6)
    assert back.texture is not None and back.texture.read_bytes() == character.texture.read_bytes()
    v = DDCTemplate(back).pose(torch.tensor(back.rest_dofs)[None])
    np.testing.assert_allclose(v[0].numpy(), back.mesh.verts, atol=1e-2)


def test_coarse_face_budget_and_watertight(character, coarse):
    F = coarse.mesh.num_faces
    assert abs(F - 3000) <= 300
    e = np.sort(np.concatenate([coarse.mesh.faces[:, [0, 1]], coarse.mesh.faces[:, [1, 2]], coarse.mesh.faces[:, [2, 0]]]), 1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert (counts == 2).all()
    assert abs(_volume(coarse.mesh.verts, coarse.mesh.faces) / _volume(character.mesh.verts, character.mesh.faces) - 1) < 0.02


def test_coarse_transferred_weights_and_labels(character, coarse):
    skin = coarse.skin
    assert skin.bones == character.skin.bones and skin.indices.shape[1] <= 6
    np.testing.assert_allclose(skin.weights.sum(1), 1.0, atol=1e-12)
    assert (np.diff(skin.weights, axis=1) <= 1e-15).all()
    # weights of a coarse vertex match the dense weights at the same place
    from scipy.spatial import cKDTree

    _, nn = cKDTree(character.mesh.verts).query(coarse.mesh.verts)
    dense0, dense1 = character.skin.dense(), skin.dense()
    assert np.abs(dense1 - dense0[nn]).sum(1).mean() < 0.15
    assert set(np.unique(coarse.segmentation)) <= set(np.unique(character.segmentation))
    assert (coarse.segmentation == 12).sum() > 50 and set(np.unique(coarse.hand_segmentation)) == {0, 1, 2}
    assert coarse.graph is character.graph, "the original graph file is reused"


def test_coarse_new_atlas_and_rebaked_texture(character, coarse):
    import cv2

    m = coarse.mesh
    assert m.has_uvs and len(m.uvs) >= m.num_verts and (m.uvs >= 0).all() and (m.uvs <= 1).all()
    new_tex = cv2.imdecode(np.frombuffer(coarse.extra["texture_png"], np.uint8), cv2.IMREAD_COLOR)[..., ::-1] / 255.0
    old_tex = cv2.imread(str(character.texture))[..., ::-1] / 255.0
    assert new_tex.shape == old_tex.shape
    # colour at points inside coarse faces = original colour at the closest original surface point
    rng = np.random.default_rng(0)
    f = rng.integers(0, m.num_faces, 2000)
    b = rng.dirichlet(np.ones(3) * 4, 2000)
    pts = (b[..., None] * m.verts[m.faces[f]]).sum(1)
    uv_new = (b[..., None] * m.uvs[m.face_uvs[f]]).sum(1)
    fo, bo, _ = closest_points_on_mesh(pts, character.mesh.verts, character.mesh.faces)
    uv_old = (bo[..., None] * character.mesh.uvs[character.mesh.face_uvs[fo]]).sum(1)
    diff = np.abs(_sample_bilinear(new_tex, uv_new) - _sample_bilinear(old_tex, uv_old)).mean(1)
    assert np.median(diff) < 0.03 and diff.mean() < 0.08


def test_coarse_written_reads_back_and_poses(character, coarse, tmp_path):
    from deliffas.geometry.motion_gen import procedural_motion

    path = write_variant(tmp_path / "coarse", coarse, "coarse")
    back = read_character(path)
    assert back.mesh.num_verts == coarse.mesh.num_verts and back.texture is not None
    assert back.graph is not None and back.segmentation is not None
    t = DDCTemplate(back, dtype=torch.float64)
    np.testing.assert_allclose(t.pose(torch.tensor(back.rest_dofs)[None])[0].numpy(), back.mesh.verts, atol=1e-9)
    m = procedural_motion(back.skeleton, 5, style="dance", rest_dofs=back.rest_dofs)
    assert torch.isfinite(t.pose(torch.tensor(m.dofs))).all()


def test_coarse_on_sample_keeps_graph_and_texture_size(sample_character):
    c = coarse_variant(sample_character, 4000, atlas_res=256, texture_size=128)
    assert abs(c.mesh.num_faces - 4000) <= 400 and c.graph.num_verts == 852
    np.testing.assert_allclose(c.skin.weights.sum(1), 1.0, atol=1e-12)
    import cv2

    assert cv2.imdecode(np.frombuffer(c.extra["texture_png"], np.uint8), cv2.IMREAD_COLOR).shape == (128, 128, 3)


def test_closest_points_brute_force():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=80.0)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)) * 60
    face, bary, dist = closest_points_on_mesh(pts, v, f)
    t = v[f]
    _, d2 = _closest_on_triangles(pts[:, None, :], t[None, :, 0], t[None, :, 1], t[None, :, 2])
    np.testing.assert_allclose(dist, np.sqrt(d2.min(1)), atol=1e-9)
    q = (bary[..., None] * v[f[face]]).sum(1)
    np.testing.assert_allclose(np.linalg.norm(q - pts, axis=1), dist, atol=1e-9)
    assert (bary >= 0).all() and np.allclose(bary.sum(1), 1)


def test_sparsify_weights():
    W = np.array([[0.1, 0.0, 0.5, 0.2, 0.05, 0.05, 0.1], [0, 0, 0, 1, 0, 0, 0]])
    idx, w = sparsify_weights(W, 3)
    np.testing.assert_array_equal(idx, [[2, 3, 0], [3, -1, -1]])
    np.testing.assert_allclose(w, [[0.5 / 0.8, 0.2 / 0.8, 0.1 / 0.8], [1, 0, 0]])
    with pytest.raises(ValueError, match="no positive weight"):
        sparsify_weights(np.zeros((1, 3)))
