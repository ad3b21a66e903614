"""Screen-space uv rendering: barycentric convention, analytic uvs, pixel centres, depth peeling."""

from __future__ import annotations


import numpy as np
import pytest

from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import (
    UVRaycaster,
    all_hits,
    build_scene,
    first_hits,
    projected_pixel_window,
    uv_inner_or_exit,
)
from deliffas.geometry.shell import offset_shell


import reference as ref  # noqa: E402  (pytest's default prepend import mode puts this folder on sys.path)

R_IN, D = 500.0, 30.0


@pytest.fixture(scope="module")
def sphere():
    v, f = ref.icosphere(3, R_IN)
    atlas = UVAtlas.from_mesh(v, f, resolution=128)
    outer = offset_shell(v, f, D)
    return v, f, outer, atlas


def test_open3d_barycentrics_are_1_minus_b1_b2_b1_b2(sphere):
    v, f, _, _ = sphere
    rng = np.random.default_rng(0)
    origins = rng.normal(size=(200, 3)) * 2000
    targets = rng.uniform(-250, 250, size=(200, 3))  # well inside the sphere: every ray hits
    dirs = targets - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, face, bary = first_hits(build_scene(v, f), origins, dirs)
    assert (face >= 0).all()
    hit_pts = origins + t[:, None] * dirs
    bary_pts = np.einsum("nk,nkc->nc", bary, v[f[face]])
    np.testing.assert_allclose(bary_pts, hit_pts, atol=2e-2)
    assert bary.min() >= -1e-5 and np.allclose(bary.sum(1), 1, atol=1e-5)
    # a permuted convention would put the point elsewhere
    wrong = np.einsum("nk,nkc->nc", bary[:, [1, 2, 0]], v[f[face]])
    assert np.abs(wrong - hit_pts).max() > 1.0


def test_uv_at_hits_is_the_analytic_uv_of_a_plane():
    size = 400.0
    v, f, uvs, fu = ref.grid_plane(4, size)
    outer = offset_shell(v, f, D)
    np.testing.assert_allclose(outer[:, 2], D)
    cam = ref.look_at([0, 0, 1000], [0, 0, 0], 40, 30, focal=60.0)
    hits = UVRaycaster(v, f, outer, UVAtlas(uvs, fu)).cast(cam)
    assert hits.uv_inner.shape == (30, 40, 2) and hits.inner_depth.shape == (30, 40)
    # independent pixel-centre rays: pixel (c, r) through (c + 0.5, r + 0.5)
    rows, cols = np.mgrid[0:30, 0:40]
    d_cam = np.stack([(cols + 0.5 - 20) / 60.0, (rows + 0.5 - 15) / 60.0, np.ones((30, 40))], -1)
    d_world = d_cam @ cam.R  # R^T d
    d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
    for z, uv, depth, hit in [(0.0, hits.uv_inner, hits.inner_depth, hits.inner_hit), (D, hits.uv_outer, hits.outer_depth, hits.outer_hit)]:
        t = (z - 1000.0) / d_world[..., 2]
        p = cam.center + t[..., None] * d_world
        inside = (np.abs(p[..., :2]) < size / 2 - 1e-3).all(-1)
        np.testing.assert_array_equal(hit, inside)
        np.testing.assert_allclose(uv[hit], p[hit][:, :2] / size + 0.5, atol=2e-6)
        np.testing.assert_allclose(depth[hit], t[hit], rtol=1e-6)
        assert np.isnan(uv[~hit]).all() and np.isinf(depth[~hit]).all()
    assert not hits.outer_exit_hit.any()  # an open plane has no second outer hit
    assert hits.inner_hit.sum() > 100


def test_depth_peeling_orders_inner_between_outer_hits(sphere):
    v, f, outer, atlas = sphere
    cam = ref.look_at([0, 0, 3000], [0, 0, 0], 96, 96, focal=110.0)
    hits = UVRaycaster(v, f, outer, atlas).cast(cam)
    hi = hits.inner_hit
    assert hi.sum() > 1000
    assert np.all(hits.outer_hit[hi]) and np.all(hits.outer_exit_hit[hi])
    assert np.all(hits.outer_depth[hi] <= hits.inner_depth[hi])
    assert np.all(hits.inner_depth[hi] <= hits.outer_exit_depth[hi])
    # shell thickness along a central ray is about d
    c = (48, 48)
    assert abs(hits.inner_depth[c] - hits.outer_depth[c] - D) < 1.0
    # rays that cross only the shell ring still exit it
    ring = hits.outer_hit & ~hi
    assert ring.sum() > 20
    assert np.all(hits.outer_exit_hit[ring])
    assert np.all(hits.outer_exit_depth[ring] > hits.outer_depth[ring])
    uv, from_outer = uv_inner_or_exit(hits)
    np.testing.assert_array_equal(from_outer, ring)
    np.testing.assert_array_equal(uv[ring], hits.uv_outer_exit[ring])
    np.testing.assert_array_equal(uv[hi], hits.uv_inner[hi])
    assert np.isnan(uv[~hits.outer_hit]).all()


def test_ray_missing_inner_takes_outer_exit(sphere):
    v, f, outer, atlas = sphere
    rc = UVRaycaster(v, f, outer, atlas)
    origins = np.array([[515.0, 0.0, 3000.0], [560.0, 0.0, 3000.0], [0.0, 0.0, 3000.0]])
    dirs = np.tile([0.0, 0.0, -1.0], (3, 1))
    h = rc.cast_rays(origins, dirs)
    assert h.inner_hit.tolist() == [False, False, True]
    assert h.outer_hit.tolist() == [True, False, True]
    assert h.outer_exit_hit.tolist() == [True, False, True]
    # the exit is the far side of the shell: z of the exit point is about -sqrt(530^2 - 515^2)
    z_exit = 3000.0 - h.outer_exit_depth[0]
    assert abs(z_exit + np.sqrt((R_IN + D) ** 2 - 515.0**2)) < 15.0
    uv, from_outer = uv_inner_or_exit(h)
    assert from_outer.tolist() == [True, False, False]
    np.testing.assert_array_equal(uv[0], h.uv_outer_exit[0])


def test_recast_and_list_peeling_agree(sphere):
    v, f, outer, atlas = sphere
    cam = ref.look_at([0, 900, 2800], [0, 0, 0], 64, 64, focal=80.0)
    a = UVRaycaster(v, f, outer, atlas, peel="recast").cast(cam)
    b = UVRaycaster(v, f, outer, atlas, peel="list").cast(cam)
    np.testing.assert_array_equal(a.outer_face, b.outer_face)
    np.testing.assert_array_equal(a.outer_exit_hit, b.outer_exit_hit)
    np.testing.assert_array_equal(a.outer_exit_face, b.outer_exit_face)
    m = a.outer_exit_hit
    np.testing.assert_allclose(a.outer_exit_depth[m], b.outer_exit_depth[m], atol=5e-3)
    np.testing.assert_allclose(a.uv_outer_exit[m], b.uv_outer_exit[m], atol=1e-5)


def test_all_hits_lists_both_sides(sphere):
    v, f, outer, atlas = sphere
    ray_ids, t, face, _ = all_hits(build_scene(v, f), np.array([[1.23, 4.56, 3000]]), np.array([[0.0, 0, -1]]))
    assert ray_ids.tolist() == [0, 0] and t[0] < t[1]
    np.testing.assert_allclose(t, [2500.0, 3500.0], atol=10.0)
    # through a vertex (the icosphere has one on the z axis) open3d lists one hit per face there;
    # both peeling methods still return the far side as the exit
    ray_ids, t, _, _ = all_hits(build_scene(v, f), np.array([[0.0, 0, 3000]]), np.array([[0.0, 0, -1]]))
    assert len(t) > 2
    for peel in ("recast", "list"):
        h = UVRaycaster(v, f, outer, atlas, peel=peel).cast_rays(np.array([[0.0, 0, 3000]]), np.array([[0.0, 0, -1]]))
        np.testing.assert_allclose([h.outer_depth[0], h.outer_exit_depth[0]], [3000 - R_IN - D, 3000 + R_IN + D], atol=1e-2)


def test_mask_subset_and_batch_match_full_image(sphere):
    v, f, outer, atlas = sphere
    rc = UVRaycaster(v, f, outer, atlas)
    cams = [ref.look_at([3000 * np.sin(a), 0, 3000 * np.cos(a)], [0, 0, 0], 48, 40, focal=60.0) for a in (0.0, 1.0)]
    full = rc.cast(cams[0])
    mask = full.outer_hit.copy()
    mask[::3] = False
    sub = rc.cast(cams[0], mask=mask)
    rows, cols = np.nonzero(mask)
    np.testing.assert_array_equal(sub.pixels, np.stack([cols, rows], 1))
    np.testing.assert_array_equal(sub.inner_face, full.inner_face[mask])
    np.testing.assert_allclose(sub.uv_outer_exit, full.uv_outer_exit[mask])
    batch = rc.cast_batch(cams)
    assert batch.uv_inner.shape == (2, 40, 48, 2)
    for k, cam in enumerate(cams):
        single = rc.cast(cam)
        np.testing.assert_array_equal(batch.inner_face[k], single.inner_face)
        np.testing.assert_allclose(batch.uv_outer[k], single.uv_outer, equal_nan=True)
    with pytest.raises(ValueError, match="size"):
        rc.cast_batch([cams[0], ref.look_at([0, 0, 3000], [0, 0, 0], 10, 10, focal=20.0)])
    with pytest.raises(ValueError, match="mask"):
        rc.cast(cams[0], mask=np.ones((3, 3), bool))


def test_raycaster_checks(sphere, unchecked):
    v, f, outer, atlas = sphere
    with unchecked(), pytest.raises(ValueError, match="outer_verts"):
        UVRaycaster(v, f, outer[:-1], atlas)
    with unchecked(), pytest.raises(ValueError, match="peel"):
        UVRaycaster(v, f, outer, atlas, peel="zbuffer")
    with unchecked(), pytest.raises(ValueError, match="exits"):
        UVRaycaster(v, f, outer, atlas).cast_foreground(ref.look_at([0, 0, 3000], [0, 0, 0], 8, 8, 10.0), exits="some")
    with unchecked(), pytest.raises(ValueError, match="atlas"):
        UVRaycaster(v, f[:-1], outer, atlas)


def test_template_raycast_from_3m(sample_dir):
    v, f, uvs, fu = ref.read_obj_minimal(sample_dir / "ddc.obj")
    outer = offset_shell(v, f, D)
    centre = (v.min(0) + v.max(0)) / 2
    cam = ref.look_at(centre + [0, 0, 3000], centre, 256, 256, focal=400.0)
    hits = UVRaycaster(v, f, outer, UVAtlas.from_mesh(v, f, uvs, fu)).cast(cam)
    hi = hits.inner_hit
    assert 2000 < hi.sum() < 0.5 * 256 * 256
    assert np.all(hits.outer_hit[hi])
    assert np.mean(hits.outer_depth[hi] <= hits.inner_depth[hi]) == 1.0
    # the 30 mm shell of the template folds on itself in creases (shell_report counts ~1700
    # faces), so some second outer hits come before the inner hit; DELIFFAS only uses the
    # second hit where the inner surface is missed
    assert np.mean(hits.inner_depth[hi] <= hits.outer_exit_depth[hi]) > 0.9
    uv, from_outer = uv_inner_or_exit(hits)
    assert from_outer.sum() > 0
    ok = ~np.isnan(uv[..., 0])
    assert (uv[ok] >= -1e-6).all() and (uv[ok] <= 1 + 1e-6).all()


def test_box_culling_keeps_every_hit(sphere):
    """cast_rays hands open3d only the rays meeting the surfaces' box; every other ray must miss."""
    v, f, outer, atlas = sphere
    rc = UVRaycaster(v, f, outer, atlas)
    rng = np.random.default_rng(1)
    origins = rng.uniform(-1500, 1500, size=(4000, 3))
    origins[:500] = rng.uniform(-200, 200, size=(500, 3))  # inside both surfaces
    dirs = rng.normal(size=(4000, 3))
    dirs[np.arange(500, 1000), rng.integers(0, 3, 500)] = 0.0  # zero components: 0 x inf in the slab test
    origins[500:600, 0] = rc.box_lo[0]  # origin on a slab plane with a zero component: 0 x inf = NaN
    dirs[500:600, 0] = 0.0
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    h = rc.cast_rays(origins, dirs)
    inner_scene, outer_scene = build_scene(v, f), build_scene(outer, f)
    t_in, f_in, _ = first_hits(inner_scene, origins, dirs)
    t_out, f_out, _ = first_hits(outer_scene, origins, dirs)
    np.testing.assert_array_equal(h.inner_face, f_in)
    np.testing.assert_array_equal(h.outer_face, f_out)
    np.testing.assert_array_equal(h.inner_depth, t_in)
    assert 0 < h.outer_hit.sum() < len(origins)  # both culled and cast rays occur


@pytest.mark.parametrize("peel", ["recast", "list"])
def test_foreground_cast_equals_full_image_restricted_to_hits(sphere, peel):
    """cast_foreground casts only the projected window; it must lose no hit pixel and change no hit."""
    v, f, outer, atlas = sphere
    rc = UVRaycaster(v, f, outer, atlas, peel=peel)
    cams = {
        "centred": ref.look_at([0, 0, 3000], [0, 0, 0], 48, 40, focal=60.0),
        "clipped by the image": ref.look_at([0, 0, 3000], [900, 600, 0], 48, 40, focal=60.0),
        "inside (vertices behind)": ref.look_at([0, 0, 300], [0, 0, 0], 32, 24, focal=12.0),
        "looking away": ref.look_at([0, 0, 3000], [0, 0, 6000], 16, 12, focal=20.0),
    }
    for name, cam in cams.items():
        full = rc.cast(cam)
        hit = full.inner_hit | full.outer_hit
        fg = rc.cast_foreground(cam)
        rows, cols = np.nonzero(hit)
        np.testing.assert_array_equal(fg.pixels, np.stack([cols, rows], 1), err_msg=name)
        for field in ("inner_face", "outer_face", "outer_exit_face", "inner_depth", "outer_exit_depth"):
            np.testing.assert_array_equal(getattr(fg, field), getattr(full, field)[hit], err_msg=f"{name} {field}")
        np.testing.assert_array_equal(fg.uv_outer_exit, full.uv_outer_exit[hit], err_msg=name)
        # exits only where the inner surface is missed: the same DELIFFAS inner sample
        lean = rc.cast_foreground(cam, exits="inner_miss")
        np.testing.assert_array_equal(lean.pixels, fg.pixels)
        np.testing.assert_array_equal(uv_inner_or_exit(lean)[0], uv_inner_or_exit(fg)[0], err_msg=name)
        if peel == "recast":
            assert not (lean.outer_exit_hit & lean.inner_hit).any()
        window = projected_pixel_window(cam, rc.hull_points)
        if name.startswith("inside"):
            assert window is None and hit.all()
        elif name == "looking away":
            assert len(fg.pixels) == 0
        else:
            c0, r0, c1, r1 = window
            assert c0 <= cols.min() and cols.max() < c1 and r0 <= rows.min() and rows.max() < r1
            assert (c1 - c0) * (r1 - r0) < hit.size  # it does cull
        if name == "clipped by the image":
            assert hit[:, 0].any() and c0 == 0 and hit[-1].any() and r1 == cam.height  # crosses left and bottom edges


def test_projected_pixel_window_bounds_and_edge_cases():
    cam = ref.look_at([0, 0, 1000], [0, 0, 0], 40, 30, focal=50.0)
    # a point on the optical axis projects to the principal point (20, 15): centres 19.5 .. 20.5 with pad 1
    assert projected_pixel_window(cam, np.zeros((1, 3)), pad=1.0) == (19, 14, 21, 16)
    assert projected_pixel_window(cam, np.zeros((0, 3))) == (0, 0, 0, 0)
    assert projected_pixel_window(cam, np.array([[0.0, 0, 1500]])) is None  # behind the camera
    assert projected_pixel_window(cam, np.array([[np.nan, 0, 0]])) is None
    c0, r0, c1, r1 = projected_pixel_window(cam, np.array([[1e6, 1e6, 0.0]]))  # far off the image
    assert (c1 - c0) * (r1 - r0) == 0


def test_foreground_cast_of_a_fraction_is_a_random_subset_of_the_full_one(sphere):
    """``fraction`` casts each window pixel with that probability: the hits are those of the full cast."""
    v, f, outer, atlas = sphere
    rc = UVRaycaster(v, f, outer, atlas)
    cam = ref.look_at([0, 0, 3000], [0, 0, 0], 48, 40, focal=60.0)
    full = rc.cast_foreground(cam, exits="inner_miss")
    part = rc.cast_foreground(cam, exits="inner_miss", fraction=0.25, rng=np.random.default_rng(3))
    key = lambda p: p[:, 1] * cam.width + p[:, 0]  # noqa: E731
    rows = np.searchsorted(key(full.pixels), key(part.pixels))
    np.testing.assert_array_equal(full.pixels[rows], part.pixels)  # a subset, in row-major order
    np.testing.assert_array_equal(full.uv_outer[rows], part.uv_outer)
    np.testing.assert_array_equal(uv_inner_or_exit(full)[0][rows], uv_inner_or_exit(part)[0])
    assert 0.15 * len(full.pixels) < len(part.pixels) < 0.35 * len(full.pixels)
    with pytest.raises(ValueError, match="fraction"):
        rc.cast_foreground(cam, fraction=0.5)  # no rng
