"""Offset shells: distances, safe offsets between close parts, folds, and the validity report."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from deliffas.geometry.shell import (
    ShellConfig,
    boundary_edges,
    fold_distances,
    offset_shell,
    safe_offsets,
    self_intersecting_faces,
    shell_offsets,
    shell_report,
)


import reference as ref  # noqa: E402  (pytest's default prepend import mode puts this folder on sys.path)

D = 30.0
GAP = 40.0  # between the two capsules: < 2 D, so their 30 mm shells overlap


@pytest.fixture(scope="module")
def two_capsules():
    """Two parallel y-aligned capsules (radius 100) with a 40 mm gap, like an arm by the torso."""
    a = ref.capsule(100.0, 400.0, center=(-100.0 - GAP / 2, 0.0, 0.0))
    b = ref.capsule(100.0, 400.0, center=(100.0 + GAP / 2, 0.0, 0.0))
    return ref.concat_meshes(a, b)


def test_shell_distance_is_d_on_a_sphere():
    v, f = ref.icosphere(3, 500.0)
    outer = offset_shell(v, f, D)
    np.testing.assert_allclose(np.linalg.norm(outer - v, axis=1), D)
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    dist = scene.compute_distance(o3d.core.Tensor(outer.astype(np.float32))).numpy()
    np.testing.assert_allclose(dist, D, rtol=2e-3)  # point-to-inner-surface distance
    # points inside the outer faces are about d from the inner surface too
    dist_c = scene.compute_distance(o3d.core.Tensor(outer[f].mean(1).astype(np.float32))).numpy()
    np.testing.assert_allclose(dist_c, D, rtol=0.02)


def test_offset_shell_per_vertex_batched_torch(unchecked):
    v, f = ref.icosphere(2, 500.0)
    offsets = np.linspace(10, 30, len(v))
    out_np = offset_shell(v, f, offsets)
    np.testing.assert_allclose(np.linalg.norm(out_np - v, axis=1), offsets)
    batch = torch.tensor(np.stack([v, 1.1 * v]), dtype=torch.float64)
    out_t = offset_shell(batch, torch.as_tensor(f), torch.as_tensor(offsets))
    assert out_t.shape == batch.shape and out_t.dtype == torch.float64
    np.testing.assert_allclose(out_t[0].numpy(), out_np)
    with unchecked(), pytest.raises(ValueError, match="offsets"):
        offset_shell(v, f, offsets[:-1])


def test_safe_offsets_keep_d_on_a_convex_mesh():
    v, f = ref.icosphere(3, 500.0)
    d = safe_offsets(v, f, D)
    np.testing.assert_allclose(d, D)  # own-neighbourhood hits never clamp


def test_safe_offsets_clamp_between_close_parts(two_capsules):
    v, f = two_capsules
    d = safe_offsets(v, f, D, repair_iterations=0)  # the normal-ray limit alone
    # the lines of each capsule facing the other (their ends at |y| = 200 have tilted normals)
    closest = (np.abs(np.abs(v[:, 0]) - GAP / 2) < 1e-6) & (np.abs(v[:, 1]) < 190)
    assert closest.sum() >= 10
    # normal rays meet the other capsule at 40 mm (a little more where the triangulation tilts them)
    assert d[closest].max() <= 0.45 * GAP * 1.01
    far_side = np.abs(v[:, 0]) > 150.0
    np.testing.assert_allclose(d[far_side], D)
    assert d.min() >= ShellConfig().min_offset_mm
    # slope limit: the offset ramps up at most 0.5 mm per mm along edges
    from deliffas.geometry.shell import mesh_edges

    e, _, _ = mesh_edges(f)
    length = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    assert np.all(np.abs(d[e[:, 0]] - d[e[:, 1]]) <= 0.5 * length + 1e-6)


def test_report_flags_crossing_shell_and_clears_safe_one(two_capsules):
    v, f = two_capsules
    naive = shell_report(v, f, offset_shell(v, f, D), offsets=np.full(len(v), D))
    assert naive.num_self_intersecting_faces > 0 and naive.num_clamped == 0
    cfg = ShellConfig(offset_mm=D, safe=True)
    d = shell_offsets(v, f, cfg)
    safe = shell_report(v, f, offset_shell(v, f, d), offsets=d, offset_mm=cfg.offset_mm)
    assert safe.num_self_intersecting_faces == 0
    assert safe.num_clamped > 0 and safe.offset_min_mm <= 0.45 * GAP + 1e-6 and safe.offset_mean_mm < D
    assert safe.watertight and safe.num_inner_self_intersecting_faces == 0
    json.dumps(safe.to_dict())
    np.testing.assert_allclose(shell_offsets(v, f, ShellConfig()), D)


def test_self_intersections_match_loop_oracle():
    # two tetrahedra pushed into each other, plus a far one
    tet_v = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 0], [0, 0, 100]])
    tet_f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    v, f = ref.concat_meshes((tet_v, tet_f), (tet_v + [30, 20, 10], tet_f), (tet_v + [500, 0, 0], tet_f))
    got = set(self_intersecting_faces(v, f).tolist())
    expected = set()
    for i, j in itertools.combinations(range(len(f)), 2):
        if set(f[i]) & set(f[j]):
            continue
        for a, b in [(f[i], f[j]), (f[j], f[i])]:
            for k in range(3):
                if ref.segment_hits_triangle(v[a[k]], v[a[(k + 1) % 3]], *v[b]):
                    expected |= {i, j}
    assert expected and got == expected
    assert not set(range(8, 12)) & got  # the far tetrahedron is clean


def test_watertight_report_flags_a_hole():
    v, f = ref.icosphere(2, 500.0)
    ok = shell_report(v, f, offset_shell(v, f, D))
    assert ok.watertight and ok.num_boundary_edges == 0 and ok.num_self_intersecting_faces == 0
    holed = f[1:]
    rep = shell_report(v, holed, offset_shell(v, holed, D))
    assert not rep.watertight and rep.num_boundary_edges == 3
    assert rep.boundary_vertex_ids == sorted(f[0].tolist())
    assert boundary_edges(holed).shape == (3, 2)


def test_camera_rays_meet_outer_before_inner():
    v, f = ref.icosphere(3, 500.0)
    cams = [ref.look_at([3000 * np.sin(a), 500, 3000 * np.cos(a)], [0, 0, 0], 48, 48, focal=60.0) for a in (0.0, 2.0)]
    good = shell_report(v, f, offset_shell(v, f, D), cams)
    assert good.num_rays_inner > 500 and good.outer_first_fraction == 1.0
    inside = shell_report(v, f, offset_shell(v, f, -D), cams)  # "outer" surface inside the inner
    assert inside.outer_first_fraction == 0.0


def test_fold_distances():
    v, f = ref.icosphere(3, 500.0)
    assert np.isinf(fold_distances(v, f)).all()  # convex: offsetting outward never folds
    inv = fold_distances(v, f[:, ::-1])  # inward normals: faces collapse near the centre
    assert np.all((inv > 400) & (inv < 600))  # about the radius (area-weighted normals tilt a bit)
    v2, f2 = ref.icosphere(2, 500.0)
    d = safe_offsets(v2, f2[:, ::-1], 1000.0, fold_fraction=0.5, min_offset_mm=0.0, repair_iterations=0)
    assert d.max() <= 0.5 * 600


def test_template_shell(sample_dir):
    v, f, _, _ = ref.read_obj_minimal(sample_dir / "ddc.obj")
    centre = (v.min(0) + v.max(0)) / 2
    cam = ref.look_at(centre + [0, 0, 3000], centre, 128, 128, focal=200.0)
    rep = shell_report(v, f, offset_shell(v, f, D), [cam], np.full(len(v), D))
    assert rep.watertight and rep.num_verts == 5514 and rep.num_inner_self_intersecting_faces == 0
    assert rep.outer_first_fraction == 1.0
    assert rep.num_self_intersecting_faces > 0  # a uniform 30 mm shell folds in creases
    cfg = ShellConfig(safe=True)
    d = shell_offsets(v, f, cfg)
    assert 0 < (d < D).sum() < len(v) and d.min() >= cfg.min_offset_mm
    assert len(self_intersecting_faces(offset_shell(v, f, d), f)) == 0  # repaired
