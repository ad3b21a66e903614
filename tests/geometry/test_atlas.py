"""UV atlases and texel tables: loop oracle, gutter extrapolation, xatlas mapping, the real template."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from deliffas.geometry.atlas import GUTTER_BARY_MIN, UVAtlas, texel_centers_uv, uv_texel_table


import reference as ref  # noqa: E402  (pytest's default prepend import mode puts this folder on sys.path)


def _small_atlas(seed=0):
    """8 faces (a 2 x 2 quad grid) with jittered per-vertex uvs inside [0.1, 0.9]^2 plus one
    separate chart (a duplicated face with its own uvs) -> 9 faces."""
    v, f, uvs, fu = ref.grid_plane(2, 400.0)
    rng = np.random.default_rng(seed)
    uvs = 0.1 + 0.6 * uvs + rng.uniform(-0.03, 0.03, uvs.shape)
    extra_uv = np.array([[0.75, 0.1], [0.95, 0.3], [0.78, 0.45]])
    uvs = np.concatenate([uvs, extra_uv])
    f = np.concatenate([f, f[:1]])
    fu = np.concatenate([fu, [[len(uvs) - 3, len(uvs) - 2, len(uvs) - 1]]])
    return v, f, UVAtlas(uvs, fu)


def test_texel_centre_convention():
    c = texel_centers_uv(4)
    np.testing.assert_allclose(c[0, 0], [0.125, 0.875])  # row 0 is the top (v near 1)
    np.testing.assert_allclose(c[3, 1], [0.375, 0.125])


@pytest.mark.parametrize("seed", [0, 1])
def test_coverage_matches_loop_oracle(seed):
    _, _, atlas = _small_atlas(seed)
    S = 16
    table = uv_texel_table(atlas, S, gutter=0)
    best = ref.texel_coverage_loop(atlas.uvs, atlas.face_uvs, S)
    expected = np.zeros((S, S), bool)
    for (i, j), cands in best.items():
        expected[i, j] = True
        f = int(table.face[i, j])
        assert f in cands, f"texel {(i, j)}: face {f} not among best {sorted(cands)}"
        np.testing.assert_allclose(table.bary[i, j], cands[f], atol=1e-6)
    np.testing.assert_array_equal(table.covered, expected)
    np.testing.assert_array_equal(table.valid, expected)
    assert np.all(table.face[~expected] == -1) and np.all(table.bary[~expected] == 0)
    assert expected.sum() > 50  # the test exercises real coverage


@pytest.mark.parametrize("gutter", [1, 2])
def test_gutter_takes_nearest_face_with_extrapolated_bary(gutter):
    _, _, atlas = _small_atlas(0)
    S = 16
    table = uv_texel_table(atlas, S, gutter=gutter)
    base = uv_texel_table(atlas, S, gutter=0)
    np.testing.assert_array_equal(table.covered, base.covered)
    np.testing.assert_array_equal(table.face[base.covered], base.face[base.covered])
    rings = ref.gutter_distance_loop(base.covered, gutter)
    filled = table.valid & ~table.covered
    assert set(zip(*np.nonzero(filled))) == set(rings)
    cov_idx = np.argwhere(base.covered)
    uv = texel_centers_uv(S)
    for (i, j), d2 in rings.items():
        near = cov_idx[((cov_idx - [i, j]) ** 2).sum(1) == d2]
        assert table.face[i, j] in {int(base.face[a, b]) for a, b in near}
        # extrapolated barycentrics of this texel's own uv in that face, clamped and rescaled
        tri = atlas.corner_uvs[table.face[i, j]]
        q = ((uv[i, j, 0]) * S - 0.5, (1 - uv[i, j, 1]) * S - 0.5)
        b = ref._bary_point(q, *[(p[0] * S - 0.5, (1 - p[1]) * S - 0.5) for p in tri])
        b = np.maximum(b, GUTTER_BARY_MIN)
        np.testing.assert_allclose(table.bary[i, j], b / b.sum(), atol=1e-5)
    assert np.allclose(table.bary[table.valid].sum(-1), 1.0, atol=1e-5)
    assert table.bary[table.valid].min() >= GUTTER_BARY_MIN - 1e-6
    assert table.bary[table.valid].max() <= 1 - 2 * GUTTER_BARY_MIN + 1e-6
    assert len(rings) > 0


def test_gutter_extrapolation_is_linear_for_bilinear_lookups():
    # one big face with uv = linear map of xy: gutter texels continue the map exactly
    v = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 0]])
    uvs = np.array([[0.3, 0.3], [0.7, 0.3], [0.3, 0.7]])
    atlas = UVAtlas(uvs, np.array([[0, 1, 2]]))
    table = uv_texel_table(atlas, 32, gutter=2)
    uv = texel_centers_uv(32)
    pts = np.einsum("ijk,kc->ijc", table.bary.astype(np.float64), v)  # 3D point of each texel
    ok = table.valid & (table.bary.min(-1) > GUTTER_BARY_MIN)  # not clamped
    np.testing.assert_allclose(pts[ok][:, :2], (uv[ok] - 0.3) / 0.4 * 100, atol=1e-3)
    assert (table.valid & ~table.covered).sum() > 0


def test_zero_area_uv_faces_are_reported(caplog):
    _, _, atlas = _small_atlas(0)
    uvs = np.concatenate([atlas.uvs, [[0.5, 0.5]]])
    fu = np.concatenate([atlas.face_uvs, [[len(uvs) - 1] * 3]])
    with caplog.at_level(logging.WARNING, logger="deliffas.geometry.atlas"):
        table = uv_texel_table(UVAtlas(uvs, fu), 16)
    assert table.degenerate_faces.tolist() == [len(fu) - 1]
    assert "1 zero-area UV faces" in caplog.text
    assert not np.any(table.face == len(fu) - 1)


def test_atlas_checks(unchecked):
    with unchecked(), pytest.raises(ValueError, match="face_uvs"):
        UVAtlas(np.zeros((3, 2)), np.array([[0, 1, 3]]))
    with unchecked(), pytest.raises(ValueError, match="uvs"):
        UVAtlas(np.zeros((3, 3)), np.array([[0, 1, 2]]))
    with unchecked(), pytest.raises(ValueError, match="both"):
        UVAtlas.from_mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), uvs=np.zeros((3, 2)))
    atlas = UVAtlas(np.zeros((3, 2)), np.array([[0, 1, 2]]))
    with unchecked(), pytest.raises(ValueError):
        atlas.uvs[0, 0] = 1.0  # frozen arrays


def test_from_mesh_keeps_given_uvs():
    v, f, uvs, fu = ref.grid_plane(3)
    atlas = UVAtlas.from_mesh(v, f, uvs, fu)
    np.testing.assert_array_equal(atlas.uvs, uvs)
    np.testing.assert_array_equal(atlas.face_uvs, fu)


def test_from_mesh_xatlas_maps_back_to_original_corners():
    v, f = ref.icosphere(2, 500.0)
    atlas = UVAtlas.from_mesh(v, f, resolution=128)
    assert atlas.face_uvs.shape == f.shape
    assert len(atlas.uvs) > len(v)  # xatlas split vertices at seams: per-corner uvs
    assert atlas.uvs.min() >= 0 and atlas.uvs.max() <= 1
    # a corner's uv depends only on its (vertex, chart): same vertex and same uv index -> same
    # vertex; xatlas's vmapping was consistent with the original faces
    corner_v = f.reshape(-1)
    corner_t = atlas.face_uvs.reshape(-1)
    first_v = np.full(len(atlas.uvs), -1)
    first_v[corner_t] = corner_v
    np.testing.assert_array_equal(first_v[corner_t], corner_v)
    # charts are laid out with little distortion: uv area proportional to 3D area
    a3 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    c = atlas.corner_uvs
    e1, e2 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
    a2 = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    ratio = a2 / a3
    assert np.percentile(ratio, 95) / np.percentile(ratio, 5) < 2.0
    table = uv_texel_table(atlas, 128)
    assert set(np.unique(table.face[table.covered])) == set(range(len(f)))  # every face drawn


def test_template_texel_table(sample_dir):
    v, f, uvs, fu = ref.read_obj_minimal(sample_dir / "ddc.obj")
    assert v.shape == (5514, 3) and f.shape == (11024, 3)
    atlas = UVAtlas.from_mesh(v, f, uvs, fu)
    table = uv_texel_table(atlas, 256)
    assert table.face.shape == (256, 256)
    assert 0.3 < table.covered.mean() < 0.5
    assert table.valid.sum() > table.covered.sum()
    assert len(table.degenerate_faces) == 0
    # texels sample the 3D surface: their points lie on the mesh's faces
    pts = np.einsum("nk,nkc->nc", table.bary[table.covered], v[f[table.face[table.covered]]])
    assert np.isfinite(pts).all()
    t0 = time.perf_counter()
    big = uv_texel_table(atlas, 1024)
    elapsed = time.perf_counter() - t0
    assert big.covered.sum() > 0.3 * 1024**2
    assert elapsed < 6.0, f"S=1024 texel table took {elapsed:.2f} s (target < 2 s on an idle machine)"
