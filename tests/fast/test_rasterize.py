"""The rasteriser gives the ray caster's shaded pixels, uvs and exits; its C kernel equals its numpy version."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from deliffas.fast.rasterize import UVRasterizer, raster_kernel_available
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import UVRaycaster, uv_inner_or_exit
from deliffas.geometry.shell import offset_shell

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "geometry"))  # the geometry tests' loop references
import reference as ref  # noqa: E402

EDGE_PIXELS_MAX = 1e-3
"""At most this fraction of the shaded pixels may differ from the ray caster's (pixel centres within
float32 round-off of a triangle edge: open3d intersects in float32, the rasteriser in float64)."""


def _raycast_shaded(rc: UVRaycaster, cam):
    """(pixels, uv_inner, inner_from_outer, uv_outer) of the ray caster's shaded pixels, row-major."""
    hits = rc.cast(cam)
    uv_in, from_outer = uv_inner_or_exit(hits)
    shaded = hits.outer_hit & np.isfinite(uv_in).all(-1) & np.isfinite(hits.uv_outer).all(-1)
    rows, cols = np.nonzero(shaded)
    return rows * cam.width + cols, uv_in[shaded], from_outer[shaded], hits.uv_outer[shaded]


def _compare(rz: UVRasterizer, rc: UVRaycaster, cam, uv_tol: float = 1e-4) -> dict:
    got = rz.shaded_pixels(cam)
    pixels, uv_in, from_outer, uv_out = _raycast_shaded(rc, cam)
    common, ia, ib = np.intersect1d(pixels, got.pixels, return_indices=True)
    differ = len(pixels) + got.num_rays - 2 * len(common)
    assert differ <= EDGE_PIXELS_MAX * len(pixels) + 2, f"{differ} of {len(pixels)} shaded pixels differ"
    # at a pixel centre on an edge the two may pick different triangles: another inner source, or
    # another side of a uv seam; such pixels are bounded, every other uv agrees to uv_tol
    bound = EDGE_PIXELS_MAX * len(pixels) + 2
    same_source = from_outer[ia] == got.inner_from_outer[ib]
    assert (~same_source).sum() <= bound
    off_out = np.abs(got.uv_outer[ib] - uv_out[ia]).max(1) > uv_tol
    off_in = np.abs(got.uv_inner[ib] - uv_in[ia]).max(1)[same_source] > uv_tol
    assert off_out.sum() <= bound and off_in.sum() <= bound, f"{off_out.sum()}, {off_in.sum()} uvs differ"
    _, dirs = cam.rays()
    np.testing.assert_allclose(got.viewdir, dirs[got.pixels], atol=1e-6)
    return {"rays": len(pixels), "differ": differ, "exits": int(from_outer.sum()),
            "uv_differ": int(off_out.sum() + off_in.sum() + (~same_source).sum())}


@pytest.fixture(scope="module")
def blob():
    """A non-convex closed mesh (a squashed, dented icosphere) and its 40 mm shell, which folds in the dent."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=400.0)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    v[:, 1] *= 1.6
    v[:, 0] *= 1.0 - 0.3 * np.exp(-((v[:, 1] / 200.0) ** 2))  # a waist: rays miss inner, hit the shell
    outer = offset_shell(v, f, 40.0)
    return v, f, outer, UVAtlas.from_mesh(v, f, resolution=64)


@pytest.mark.parametrize("method", ["numpy", "native"])
@pytest.mark.parametrize("center", [[0, 0, 2500.0], [1800.0, 300.0, 1500.0], [0.0, 2600.0, 400.0]])
def test_rasterizer_matches_the_ray_caster(blob, method, center):
    if method == "native" and not raster_kernel_available():
        pytest.skip("no C compiler")
    v, f, outer, atlas = blob
    cam = ref.look_at(center, [0.0, 0.0, 0.0], 96, 80, focal=110.0)
    stats = _compare(UVRasterizer(v, f, outer, atlas, method=method), UVRaycaster(v, f, outer, atlas), cam)
    assert stats["rays"] > 500


def test_rasterizer_takes_exits_where_the_inner_surface_is_missed(blob):
    v, f, outer, atlas = blob
    cam = ref.look_at([0, 0, 2500.0], [0.0, 0.0, 0.0], 128, 128, focal=110.0)
    got = UVRasterizer(v, f, outer, atlas, method="numpy").shaded_pixels(cam)
    assert 0 < got.inner_from_outer.sum() < got.num_rays  # the silhouette's shell ring


def test_template_from_3m_matches_the_ray_caster(sample_dir):
    v, f, uvs, fu = ref.read_obj_minimal(sample_dir / "ddc.obj")
    outer = offset_shell(v, f, 30.0)
    atlas = UVAtlas.from_mesh(v, f, uvs, fu)
    centre = (v.min(0) + v.max(0)) / 2
    rz, rc = UVRasterizer(v, f, outer, atlas), UVRaycaster(v, f, outer, atlas)
    for offset, size, focal in (([0, 0, 3000], (257, 301), 400.0), ([2000, 300, 2000], (1285, 940), 1156.5)):
        stats = _compare(rz, rc, ref.look_at(centre + offset, centre, *size, focal=focal))
        assert stats["rays"] > 2000 and stats["exits"] > 0


def test_native_equals_numpy(blob):
    if not raster_kernel_available():
        pytest.skip("no C compiler")
    v, f, outer, atlas = blob
    for center in ([0, 0, 2500.0], [1800.0, 300.0, 1500.0]):
        cam = ref.look_at(center, [0.0, 0.0, 0.0], 120, 90, focal=120.0)
        a = UVRasterizer(v, f, outer, atlas, method="native").shaded_pixels(cam)
        b = UVRasterizer(v, f, outer, atlas, method="numpy").shaded_pixels(cam)
        np.testing.assert_array_equal(a.pixels, b.pixels)
        np.testing.assert_array_equal(a.inner_from_outer, b.inner_from_outer)
        np.testing.assert_allclose(a.uv_inner, b.uv_inner, atol=1e-6)
        np.testing.assert_allclose(a.uv_outer, b.uv_outer, atol=1e-6)
        np.testing.assert_allclose(a.viewdir, b.viewdir, atol=1e-6)
        for method in ("native", "numpy"):  # without view directions: the same rays
            c = UVRasterizer(v, f, outer, atlas, method=method).shaded_pixels(cam, viewdir=False)
            assert c.viewdir is None
            np.testing.assert_array_equal(c.pixels, a.pixels)
            np.testing.assert_array_equal(c.uv_inner, (a if method == "native" else b).uv_inner)


def test_vertex_behind_the_camera_returns_none(blob):
    v, f, outer, atlas = blob
    cam = ref.look_at([0, 0, 300.0], [0.0, 0.0, -1000.0], 64, 64, focal=60.0)  # inside the mesh
    assert UVRasterizer(v, f, outer, atlas).shaded_pixels(cam) is None


def test_disabled_native_falls_back(blob, monkeypatch):
    import deliffas.fast.rasterize as rasterize
    from deliffas.native import LazyLibrary

    monkeypatch.setenv("DELIFFAS_NATIVE", "0")
    monkeypatch.setattr(rasterize, "_KERNEL", LazyLibrary("rasterize", rasterize._KERNEL.source, fallback="numpy"))
    v, f, outer, atlas = blob
    cam = ref.look_at([0, 0, 2500.0], [0.0, 0.0, 0.0], 64, 64, focal=80.0)
    assert not raster_kernel_available()
    got = UVRasterizer(v, f, outer, atlas).shaded_pixels(cam)
    assert got.num_rays > 100
    with pytest.raises(RuntimeError, match="unavailable"):
        UVRasterizer(v, f, outer, atlas, method="native").shaded_pixels(cam)


def test_rasterizer_checks(blob, unchecked):
    v, f, outer, atlas = blob
    with unchecked(), pytest.raises(ValueError, match="method"):
        UVRasterizer(v, f, outer, atlas, method="gpu")
    with unchecked(), pytest.raises(ValueError, match="outer_verts"):
        UVRasterizer(v, f, outer[:-1], atlas)


def test_depth_pass_covers_the_outer_silhouette(blob):
    if not raster_kernel_available():
        pytest.skip("no C compiler")
    v, f, outer, atlas = blob
    cam = ref.look_at([0, 0, 2500.0], [0.0, 0.0, 0.0], 96, 80, focal=110.0)
    rz = UVRasterizer(v, f, outer, atlas)
    faces = rz.depth_pass(cam)
    assert (faces >= 0).sum() == rz.shaded_pixels(cam).num_rays  # every outer-covered pixel is shaded here


def test_faces_projected_beyond_the_integer_range_equal_numpy():
    """A vertex a hair in front of the camera plane projects to ~1e104 px: the kernel clips before its integer casts
    and gives the numpy version's pixels (the faces reaching into the image from there are still drawn)."""
    if not raster_kernel_available():
        pytest.skip("no C compiler")
    cam = ref.look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1000.0], 64, 48, focal=60.0)
    in_camera = np.array([[-300, -200, 1000], [300, -200, 1000], [0, 250, 1000], [300, 200, 1e-100],
                          [-250, 150, 1000]], np.float64)  # camera frame, mm
    v = (in_camera - cam.t) @ cam.R  # world = R^T (camera - t)
    f = np.array([[0, 1, 2], [1, 3, 2], [4, 0, 3]], np.int64)
    atlas = UVAtlas.from_mesh(v, f, resolution=32)
    outer = v + 30.0 * cam.R[2]  # 30 mm farther along the optical axis
    a = UVRasterizer(v, f, outer, atlas, method="native").shaded_pixels(cam)
    b = UVRasterizer(v, f, outer, atlas, method="numpy").shaded_pixels(cam)
    assert a is not None and a.num_rays > 0
    np.testing.assert_array_equal(a.pixels, b.pixels)
    np.testing.assert_allclose(a.uv_outer, b.uv_outer, atol=1e-6)
