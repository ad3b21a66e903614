"""The torch rasteriser gives the C/numpy rasteriser's shaded pixels and uvs, and so the ray caster's."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from deliffas.fast.rasterize import ShadedPixels, UVRasterizer
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.rasterize_torch import TorchUVRasterizer
from deliffas.geometry.raycast import UVRaycaster
from deliffas.geometry.shell import offset_shell

import reference as ref  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fast"))  # the C rasteriser's comparison with the caster
from test_rasterize import _compare  # noqa: E402


class _AsNumpy:
    """The torch rasteriser behind ``UVRasterizer.shaded_pixels``' numpy interface (for ``_compare``)."""

    def __init__(self, rz: TorchUVRasterizer):
        self.rz = rz

    def shaded_pixels(self, cam, viewdir: bool = True) -> ShadedPixels | None:
        got = self.rz.shaded_pixels(cam, viewdir)
        if got is None:
            return None
        return ShadedPixels(pixels=got.pixels.cpu().numpy(), uv_inner=got.uv_inner.cpu().numpy(),
                            inner_from_outer=got.inner_from_outer.cpu().numpy(), uv_outer=got.uv_outer.cpu().numpy(),
                            viewdir=None if got.viewdir is None else got.viewdir.cpu().numpy())


def _assert_equal(a: ShadedPixels, b: ShadedPixels, uv_tol: float = 1e-4) -> None:
    """The same hit set, the same inner sources, uvs within ``uv_tol``."""
    np.testing.assert_array_equal(a.pixels, b.pixels)
    np.testing.assert_array_equal(a.inner_from_outer, b.inner_from_outer)
    np.testing.assert_allclose(a.uv_inner, b.uv_inner, atol=uv_tol)
    np.testing.assert_allclose(a.uv_outer, b.uv_outer, atol=uv_tol)
    np.testing.assert_allclose(a.viewdir, b.viewdir, atol=1e-6)


def _check(v, f, outer, atlas, cameras, min_rays: int = 500) -> None:
    tz = _AsNumpy(TorchUVRasterizer(v, f, outer, atlas))
    rz, rc = UVRasterizer(v, f, outer, atlas), UVRaycaster(v, f, outer, atlas)
    exits = 0
    for cam in cameras:
        got = tz.shaded_pixels(cam)
        _assert_equal(got, rz.shaded_pixels(cam))  # the C kernel (or numpy without a compiler)
        _assert_equal(got, UVRasterizer(v, f, outer, atlas, method="numpy").shaded_pixels(cam))
        stats = _compare(tz, rc, cam)  # the ray caster, up to pixel centres on an edge
        assert stats["rays"] > min_rays
        exits += stats["exits"]
    assert exits > 0  # the peeled layer was exercised


@pytest.fixture(scope="module")
def blob():
    """A dented squashed icosphere and its 40 mm shell (as test_rasterize's)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=400.0)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    v[:, 1] *= 1.6
    v[:, 0] *= 1.0 - 0.3 * np.exp(-((v[:, 1] / 200.0) ** 2))
    return v, f, offset_shell(v, f, 40.0), UVAtlas.from_mesh(v, f, resolution=64)


def test_blob_equals_the_rasterizer_and_the_ray_caster(blob):
    v, f, outer, atlas = blob
    cams = [ref.look_at(c, [0.0, 0.0, 0.0], 96, 80, focal=110.0)
            for c in ([0, 0, 2500.0], [1800.0, 300.0, 1500.0], [0.0, 2600.0, 400.0])]
    _check(v, f, outer, atlas, cams)


def test_ddc_sample_equals_the_rasterizer_and_the_ray_caster(sample_dir):
    v, f, uvs, fu = ref.read_obj_minimal(sample_dir / "ddc.obj")
    outer = offset_shell(v, f, 30.0)
    centre = (v.min(0) + v.max(0)) / 2
    cams = [ref.look_at(centre + np.asarray(o), centre, *size, focal=focal)
            for o, size, focal in (([0, 0, 3000], (257, 301), 400.0), ([2000, 300, 2000], (1285, 940), 1156.5))]
    _check(v, f, outer, UVAtlas.from_mesh(v, f, uvs, fu), cams, min_rays=2000)


def test_smpl_body_equals_the_rasterizer_and_the_ray_caster():
    from deliffas.geometry.smpl_body import procedural_smpl, procedural_smpl_atlas

    data = procedural_smpl(seed=0, target_verts=1500)
    v, f = data.v_template * 1000.0, data.faces  # metres -> mm
    outer = offset_shell(v, f, 25.0)
    centre = (v.min(0) + v.max(0)) / 2
    cams = [ref.look_at(centre + np.asarray(o), centre, 160, 200, focal=300.0)
            for o in ([0, 0, 3000.0], [2500.0, 400.0, -1500.0])]
    _check(v, f, outer, procedural_smpl_atlas(data, resolution=128), cams)


def test_torch_inputs_and_no_view_directions(blob):
    v, f, outer, atlas = blob
    cam = ref.look_at([0, 0, 2500.0], [0.0, 0.0, 0.0], 96, 80, focal=110.0)
    a = TorchUVRasterizer(v, f, outer, atlas).shaded_pixels(cam)
    b = TorchUVRasterizer(torch.from_numpy(v).float(), torch.from_numpy(f), torch.from_numpy(outer).float(),
                          atlas).shaded_pixels(cam, viewdir=False)
    assert b.viewdir is None and a.pixels.dtype == torch.int64 and a.uv_inner.dtype == torch.float32
    assert abs(a.num_rays - b.num_rays) <= 2  # float32 vertices: edge pixels may move


def test_vertex_behind_the_camera_returns_none(blob):
    v, f, outer, atlas = blob
    cam = ref.look_at([0, 0, 300.0], [0.0, 0.0, -1000.0], 64, 64, focal=60.0)  # inside the mesh
    assert TorchUVRasterizer(v, f, outer, atlas).shaded_pixels(cam) is None


def test_empty_view_and_chunking(blob, monkeypatch):
    import deliffas.geometry.rasterize_torch as rt

    v, f, outer, atlas = blob
    away = ref.look_at([0, 0, 2500.0], [0.0, 0.0, 5000.0], 64, 64, focal=60.0)  # looks away: nothing shaded
    got = TorchUVRasterizer(v, f, outer, atlas).shaded_pixels(away)
    assert got is None or got.num_rays == 0
    cam = ref.look_at([1800.0, 300.0, 1500.0], [0.0, 0.0, 0.0], 96, 80, focal=110.0)
    whole = TorchUVRasterizer(v, f, outer, atlas).shaded_pixels(cam)
    monkeypatch.setattr(rt, "CHUNK", 1000)  # many chunks: the same pixels
    chunked = TorchUVRasterizer(v, f, outer, atlas).shaded_pixels(cam)
    assert torch.equal(whole.pixels, chunked.pixels) and torch.equal(whole.uv_inner, chunked.uv_inner)
