"""Face and vertex normals against a loop oracle, batched torch, numpy, degenerate cases."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from deliffas.geometry.mesh_ops import face_normals, vertex_normals


import reference as ref  # noqa: E402  (pytest's default prepend import mode puts this folder on sys.path)


def _bumpy_sphere(seed=0):
    v, f = ref.icosphere(2, 500.0)
    rng = np.random.default_rng(seed)
    return v * rng.uniform(0.9, 1.1, size=(len(v), 1)), f


def test_face_normals_are_unnormalised_cross_products():
    v = np.array([[0.0, 0, 0], [2, 0, 0], [0, 3, 0]])
    f = np.array([[0, 1, 2]])
    np.testing.assert_allclose(face_normals(v, f), [[0, 0, 6]])  # 2 x area, +z for CCW


def test_vertex_normals_match_loop_oracle_numpy():
    v, f = _bumpy_sphere()
    got = vertex_normals(v, f)
    assert isinstance(got, np.ndarray) and got.dtype == np.float64
    np.testing.assert_allclose(got, ref.vertex_normals_loop(v, f), atol=1e-12)


def test_vertex_normals_area_weighted_not_averaged():
    # vertex 0 shared by a big and a small face with different normals
    v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 1], [1, 0, 0.0]])
    f = np.array([[0, 1, 2], [0, 3, 4]])  # area 50 (+z) and 0.5 (+y-ish)
    n = vertex_normals(v, f)[0]
    expected = np.array([0, 0, 100.0]) + np.cross(v[3] - v[0], v[4] - v[0])
    np.testing.assert_allclose(n, expected / np.linalg.norm(expected))


def test_vertex_normals_batched_torch_matches_per_item(device):
    meshes = [_bumpy_sphere(s) for s in range(3)]
    f = meshes[0][1]
    batch = torch.tensor(np.stack([m[0] for m in meshes]), dtype=torch.float32, device=device)
    got = vertex_normals(batch, torch.as_tensor(f))
    assert got.shape == batch.shape and got.dtype == torch.float32 and got.device == batch.device
    for b, (v, _) in enumerate(meshes):
        np.testing.assert_allclose(got[b].cpu().numpy(), ref.vertex_normals_loop(v, f), atol=1e-5)


def test_vertex_normals_outward_on_sphere():
    v, f = ref.icosphere(3, 500.0)
    n = vertex_normals(v, f)
    radial = v / np.linalg.norm(v, axis=1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    assert (n * radial).sum(1).min() > 0.999  # area weighting tilts them slightly on an icosphere


def test_zero_normals_are_zero_and_flagged():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [1, 1, 0], [2, 2, 0], [3, 3, 0]])
    f = np.array([[0, 1, 2], [4, 5, 6]])  # vertex 3 isolated; face 1 degenerate (collinear)
    n, valid = vertex_normals(v, f, return_valid=True)
    assert valid.tolist() == [True, True, True, False, False, False, False]
    assert np.all(n[~valid] == 0)
    assert np.all(np.isfinite(n))


def test_shape_checks(unchecked):
    with unchecked(), pytest.raises(ValueError, match="verts"):
        vertex_normals(np.zeros((4, 2)), np.zeros((1, 3), np.int64))
    with unchecked(), pytest.raises(ValueError, match="faces"):
        face_normals(np.zeros((4, 3)), np.zeros((1, 4), np.int64))
