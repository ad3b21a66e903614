"""Normal maps through the texel gather: loop oracle, sphere geometry, naive path, temporal window."""

from __future__ import annotations


import logging

import numpy as np
import pytest
import torch

from deliffas.geometry import normal_maps as nm_module
from deliffas.geometry.atlas import UVAtlas, uv_texel_table
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.normal_maps import (
    NormalMapGather,
    fused_kernel_status,
    normal_maps,
    rasterize_normal_map_naive,
    temporal_window,
)
from deliffas.native import NATIVE_ENV, NativeLibrary, build_library


import reference as ref  # noqa: E402  (pytest's default prepend import mode puts this folder on sys.path)


def _small_mesh(seed=0):
    v, f, uvs, fu = ref.grid_plane(2, 400.0)  # 8 faces
    rng = np.random.default_rng(seed)
    v = v + rng.normal(0, 40, v.shape)
    uvs = 0.1 + 0.8 * uvs + rng.uniform(-0.03, 0.03, uvs.shape)
    return v, f, UVAtlas(uvs, fu)


@pytest.mark.parametrize("gutter", [0, 2])
def test_gather_matches_loop_oracle(gutter, device):
    v, f, atlas = _small_mesh()
    table = uv_texel_table(atlas, 16, gutter=gutter)
    rng = np.random.default_rng(1)
    vn = rng.normal(size=(2, len(v), 3))
    vn /= np.linalg.norm(vn, axis=-1, keepdims=True)
    got = normal_maps(torch.tensor(vn, device=device), f, table)
    assert got.shape == (2, 3, 16, 16) and got.dtype == torch.float64 and got.device.type == torch.device(device).type
    for b in range(2):
        expected = ref.normal_map_loop(vn[b], f, table.face, table.bary.astype(np.float64))
        np.testing.assert_allclose(got[b].cpu().numpy(), expected, atol=1e-6)
    valid = torch.as_tensor(table.valid)
    assert torch.all(got[:, :, ~valid] == 0)
    np.testing.assert_allclose(got.norm(dim=1)[:, valid].cpu().numpy(), 1.0, atol=1e-6)


def test_sphere_normal_map_is_radial():
    v, f = ref.icosphere(3, 500.0)
    atlas = UVAtlas.from_mesh(v, f, resolution=64)
    table = uv_texel_table(atlas, 64, gutter=2)
    vn = vertex_normals(torch.tensor(v, dtype=torch.float32)[None], f)
    nm = NormalMapGather.from_table(table, f).apply(vn)[0].numpy()  # (3, S, S)
    pts = np.einsum("nk,nkc->nc", table.bary[table.valid], v[f[table.face[table.valid]]])
    radial = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    cos = (nm[:, table.valid].T * radial).sum(1)
    cov = table.covered[table.valid]
    assert np.degrees(np.arccos(np.clip(cos[cov], -1, 1))).max() < 3.0
    assert np.degrees(np.arccos(np.clip(cos[~cov], -1, 1))).max() < 8.0  # extrapolated gutter


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sparse_and_gather_methods_agree(dtype, device, unchecked):
    v, f, atlas = _small_mesh(3)
    table = uv_texel_table(atlas, 16)
    gather = NormalMapGather.from_table(table, f).to(device)
    vn = torch.randn(3, len(v), 3, dtype=dtype, device=device)
    a = gather.apply(vn, method="sparse")
    b = gather.apply(vn, method="gather")
    assert a.dtype == dtype and a.shape == (3, 3, 16, 16)
    torch.testing.assert_close(a, b)
    with unchecked(), pytest.raises(ValueError, match="method"):
        gather.apply(vn, method="scatter")
    with unchecked(), pytest.raises(ValueError, match="vertex_normals"):
        gather.apply(vn[:, :-1])
    extra = torch.cat([vn, torch.randn(3, 2, 3, dtype=dtype, device=device)], dim=1)  # unused trailing vertices
    torch.testing.assert_close(gather.apply(extra), a)


@pytest.mark.parametrize("size", [13, 16])  # 13^2 texels: the AVX2 loop (8 at a time) leaves a scalar tail
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_kernel_equals_eager_paths(size, dtype):
    status = fused_kernel_status()
    if not status.available:
        pytest.skip(f"fused kernel unavailable: {status.reason}")
    v, f, atlas = _small_mesh(5)
    table = uv_texel_table(atlas, size)
    gather = NormalMapGather.from_table(table, f)
    vn = torch.randn(3, len(v) + 2, 3, dtype=dtype)  # 2 unused trailing vertices
    vn[1, 0] = 0.0  # a zero normal next to non-zero ones
    fused = gather.apply(vn, method="fused")
    assert fused.dtype == dtype and fused.shape == (3, 3, size, size)
    torch.testing.assert_close(fused, gather.apply(vn, method="sparse"), rtol=0, atol=1e-6)
    torch.testing.assert_close(fused, gather.apply(vn, method="gather"), rtol=0, atol=1e-6)
    assert torch.equal(gather.apply(vn), fused)  # "auto" takes the fused kernel on CPU
    invalid = ~torch.as_tensor(table.valid)
    assert torch.all(fused[:, :, invalid] == 0)
    # non-contiguous input, float16 output (the eager paths' cast), numpy input, unbatched input
    strided = vn.transpose(0, 1).contiguous().transpose(0, 1)
    assert torch.equal(gather.apply(strided, method="fused"), fused)
    half = gather.apply(vn, dtype=torch.float16, method="fused")
    assert half.dtype == torch.float16 and torch.equal(half, fused.to(torch.float16))
    assert np.array_equal(gather.apply(vn[2].numpy(), method="fused"), fused[2].numpy())
    # a zero interpolated normal and NaN normals follow the sparse path: 0, resp. NaN on the texels they touch
    zero = gather.apply(torch.zeros(len(v), 3, dtype=dtype), method="fused")
    assert torch.all(zero == 0)
    nan = vn[0].clone()
    nan[0] = float("nan")
    torch.testing.assert_close(gather.apply(nan, method="fused"), gather.apply(nan, method="sparse"), equal_nan=True)


def test_fused_kernel_fallback(monkeypatch, caplog):
    v, f, atlas = _small_mesh()
    gather = NormalMapGather.from_table(uv_texel_table(atlas, 8), f)
    vn = torch.randn(2, len(v), 3)
    # a failed build is reported, not raised
    monkeypatch.delenv(NATIVE_ENV, raising=False)
    monkeypatch.setenv("CC", "/nonexistent/cc")
    built = build_library("normal_maps", nm_module._KERNEL.source)
    assert built.lib is None and "nonexistent" in built.reason
    monkeypatch.setenv(NATIVE_ENV, "0")
    assert "disabled" in build_library("normal_maps", nm_module._KERNEL.source).reason
    # with the kernel unavailable, "auto" falls back to the sparse product and says why once
    monkeypatch.setattr(nm_module._KERNEL, "_built", NativeLibrary(None, "test: no compiler"))
    monkeypatch.setattr(nm_module._KERNEL, "_logged", False)
    with caplog.at_level(logging.INFO, logger="deliffas.native"):
        a = gather.apply(vn)
        gather.apply(vn)
    assert [r.levelno for r in caplog.records] == [logging.WARNING] and "test: no compiler" in caplog.text
    assert torch.equal(a, gather.apply(vn, method="sparse"))
    with pytest.raises(RuntimeError, match="test: no compiler"):
        gather.apply(vn, method="fused")


def test_float16_output_and_numpy_input():
    v, f, atlas = _small_mesh()
    table = uv_texel_table(atlas, 8)
    vn = vertex_normals(v, f)
    gather = NormalMapGather.from_table(table, f)
    out16 = gather.apply(vn[None].astype(np.float32), dtype=torch.float16)
    out32 = gather.apply(vn[None].astype(np.float32))
    assert out16.dtype == np.float16 and out32.dtype == np.float32  # numpy in, numpy out
    assert gather.apply(vn[None], dtype=np.float16).dtype == np.float16  # a numpy dtype works too
    np.testing.assert_allclose(out16.astype(np.float32), out32, atol=1e-3)
    # unbatched (V, 3) input gives (3, S, S)
    assert gather.apply(vn).shape == (3, 8, 8)


def test_naive_per_frame_rasterisation_equals_gather():
    v, f, atlas = _small_mesh()
    vn = np.stack([vertex_normals(v, f), -vertex_normals(v, f)])
    table = uv_texel_table(atlas, 16)
    fast = normal_maps(vn, f, table)
    slow = rasterize_normal_map_naive(vn, f, atlas, 16)
    assert isinstance(fast, np.ndarray) and isinstance(slow, np.ndarray)
    np.testing.assert_allclose(fast, slow, rtol=1.3e-6, atol=1e-5)


def test_zero_interpolated_normal_is_zero():
    v, f, atlas = _small_mesh()
    table = uv_texel_table(atlas, 16, gutter=0)
    vn = np.zeros((len(v), 3))
    out = normal_maps(vn, f, table)
    assert np.all(out == 0) and np.all(np.isfinite(out))


def test_gather_rejects_mismatched_faces():
    _, f, atlas = _small_mesh()
    table = uv_texel_table(atlas, 8)
    with pytest.raises(ValueError, match="face"):
        NormalMapGather.from_table(table, f[:3])


def _frames(num=5, S=4):
    return np.stack([np.full((3, S, S), k, np.float32) for k in range(num)])


def test_temporal_window_stacks_and_clamps():
    maps = _frames()
    out = temporal_window(maps, np.array([0, 3, 1]), 2)
    assert out.shape == (3, 9, 4, 4)
    # channel block k holds frame max(f - k, 0)
    assert [out[0, 3 * k, 0, 0] for k in range(3)] == [0, 0, 0]
    assert [out[1, 3 * k, 0, 0] for k in range(3)] == [3, 2, 1]
    assert [out[2, 3 * k, 0, 0] for k in range(3)] == [1, 0, 0]
    t = temporal_window(torch.from_numpy(maps), torch.tensor([0, 3, 1]), 2)
    np.testing.assert_array_equal(t.numpy(), out)
    assert temporal_window(maps, np.array([4]), 0).shape == (1, 3, 4, 4)


def test_temporal_window_checks(unchecked):
    maps = _frames()
    with unchecked(), pytest.raises(ValueError, match="rows"):
        temporal_window(maps, np.array([5]), 2)
    with unchecked(), pytest.raises(ValueError, match="maps_per_frame"):
        temporal_window(maps[:, :2], np.array([1]), 2)
    with unchecked(), pytest.raises(ValueError, match="window"):
        temporal_window(maps, np.array([1]), -1)


def test_template_normal_maps(sample_dir):
    v, f, uvs, fu = ref.read_obj_minimal(sample_dir / "ddc.obj")
    table = uv_texel_table(UVAtlas.from_mesh(v, f, uvs, fu), 256)
    gather = NormalMapGather.from_table(table, f)
    vn = vertex_normals(torch.tensor(v, dtype=torch.float32)[None], f)
    nm = gather.apply(vn, dtype=torch.float16)
    assert nm.shape == (1, 3, 256, 256)
    lengths = nm.float().norm(dim=1)[0]
    valid = torch.as_tensor(table.valid)
    assert torch.all(lengths[~valid] == 0)
    assert (lengths[valid] - 1).abs().max() < 2e-3
