"""The array policy of the geometry API (docs/conventions.md, "Arrays"), one test per function family.

Array functions return the kind they were given: numpy in -> numpy out, torch in -> torch out in the
input's floating dtype and on its device. Torch-only functions (templates, sampling, SMPL maths) say
so and refuse numpy with a TypeError naming the argument and the numpy boundary; numpy records
(atlas, texel tables, ray casting, rasterising) take either kind and hold numpy.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.geometry.atlas import TexelTable, UVAtlas, texel_centers_uv, uv_texel_table
from deliffas.geometry.mesh_ops import face_normals, vertex_normals
from deliffas.geometry.normal_maps import NormalMapGather, normal_maps, rasterize_normal_map_naive, temporal_window
from deliffas.fast.rasterize import ShadedPixels, UVRasterizer
from deliffas.geometry.raycast import RaycastHits, UVRaycaster
from deliffas.geometry.sampling import sample_uv
from deliffas.geometry.shell import (
    ShellConfig,
    fold_distances,
    mesh_edges,
    offset_shell,
    safe_offsets,
    self_intersecting_faces,
    shell_offsets,
)
from deliffas.geometry.skinning import dqs, lbs
from deliffas.geometry.smpl import batch_rodrigues, smpl_lbs

import reference as ref  # noqa: E402  (pytest's default prepend import mode puts this folder on sys.path)

FLOAT_DTYPES = [torch.float32, torch.float64]


@pytest.fixture(scope="module")
def sphere():
    v, f = ref.icosphere(2, 500.0)
    return v, f, UVAtlas.from_mesh(v, f, resolution=64)


def _as(kind: str, x: np.ndarray, dtype: torch.dtype, device: str):
    """``x`` as numpy of ``dtype``'s numpy twin, or as a tensor of ``dtype`` on ``device``; ints stay ints."""
    t = torch.as_tensor(x)
    if t.is_floating_point():
        t = t.to(dtype)
    return t.numpy() if kind == "numpy" else t.to(device)


def _assert_kind(out, kind: str, dtype: torch.dtype, device: str, floating: bool = True) -> None:
    if kind == "numpy":
        assert isinstance(out, np.ndarray), type(out)
        if floating:
            assert out.dtype == torch.empty(0, dtype=dtype).numpy().dtype, out.dtype
    else:
        assert isinstance(out, torch.Tensor), type(out)
        assert out.device.type == torch.device(device).type
        if floating:
            assert out.dtype == dtype, out.dtype


KINDS = pytest.mark.parametrize("kind", ["numpy", "torch"])
DTYPES = pytest.mark.parametrize("dtype", FLOAT_DTYPES)


# ------------------------------------------------------------------------------------ mesh ops
@KINDS
@DTYPES
def test_mesh_ops(sphere, kind, dtype, device):
    v, f, _ = sphere
    verts, faces = _as(kind, v, dtype, device), _as(kind, f, dtype, device)
    _assert_kind(face_normals(verts, faces), kind, dtype, device)
    normals, valid = vertex_normals(verts, faces, return_valid=True)
    _assert_kind(normals, kind, dtype, device)
    _assert_kind(valid, kind, dtype, device, floating=False)


# ------------------------------------------------------------------------------------ skinning
@KINDS
@DTYPES
def test_lbs_and_dqs(kind, dtype, device):
    rng = np.random.default_rng(0)
    V, Bn, B = 7, 3, 2
    rest = rng.normal(size=(V, 3)) * 100
    dense = rng.random((V, Bn))
    dense /= dense.sum(1, keepdims=True)
    T = np.tile(np.eye(4), (B, Bn, 1, 1))
    T[..., :3, 3] = rng.normal(size=(B, Bn, 3))
    indices = np.argsort(-dense, axis=1)
    weights = np.take_along_axis(dense, indices, 1)
    args = [_as(kind, a, dtype, device) for a in (rest, dense, T)]
    out = lbs(*args)
    _assert_kind(out, kind, dtype, device)
    out_dq = dqs(*[_as(kind, a, dtype, device) for a in (rest, indices, weights, T)])
    _assert_kind(out_dq, kind, dtype, device)
    # pure translations: both skinnings move every vertex by the weighted translation
    expect = rest + np.einsum("vb,nbk->nvk", dense, T[..., :3, 3])
    np.testing.assert_allclose(np.asarray(torch.as_tensor(out).cpu()), expect, rtol=1e-5, atol=1e-3)


# ------------------------------------------------------------------------------------ posing
def test_template_pose_is_torch_only_and_pose_frames_is_the_numpy_boundary(procedural_character_path, unchecked):
    from deliffas.data.posing import pose_frames
    from deliffas.geometry.motion_gen import procedural_motion
    from deliffas.geometry.templates import build_template, ddc_spec
    from deliffas.io.formats.dynacap.character import read_character
    from deliffas.io.motion import Motion

    character = read_character(procedural_character_path)
    spec = ddc_spec(procedural_character_path)
    template = build_template(spec, dtype=torch.float64)
    dofs = procedural_motion(character.skeleton, 3, seed=0, rest_dofs=character.rest_dofs).dofs
    with torch.no_grad():
        assert template.pose(torch.as_tensor(dofs, dtype=torch.float32)).dtype == torch.float64  # the template's
        posed = template.pose(torch.as_tensor(dofs))
    assert isinstance(posed, torch.Tensor) and posed.dtype == torch.float64
    with pytest.raises(TypeError, match="dofs"):  # the test run's annotation check
        template.pose(dofs)
    with unchecked(), pytest.raises(TypeError, match="dofs.*pose_frames"):  # the library's own
        template.pose(dofs)
    # frame numbers, not rows: a motion starting at frame 100
    motion = Motion(np.array([100, 101, 102]), dofs)
    verts, _ = pose_frames(spec, motion, [102, 100])
    assert isinstance(verts, np.ndarray) and verts.dtype == np.float64 and verts.shape[0] == 2
    np.testing.assert_allclose(verts, posed.numpy()[[2, 0]], atol=1e-9)
    verts32, _ = pose_frames(spec, motion, [101], dtype=torch.float32)
    assert verts32.dtype == np.float32
    with pytest.raises(ValueError, match="frame 2 not in motion"):
        pose_frames(spec, motion, [2])  # a row number is not a frame number


# ------------------------------------------------------------------------------------ shells
@KINDS
@DTYPES
def test_shells(sphere, kind, dtype, device):
    v, f, _ = sphere
    verts, faces = _as(kind, v, dtype, device), _as(kind, f, dtype, device)
    offsets = shell_offsets(verts, faces, ShellConfig(offset_mm=30.0))
    _assert_kind(offsets, kind, dtype, device)
    _assert_kind(offset_shell(verts, faces, offsets), kind, dtype, device)
    _assert_kind(offset_shell(verts, faces, 30.0), kind, dtype, device)
    safe = safe_offsets(verts, faces, 30.0, repair_iterations=1)
    _assert_kind(safe, kind, dtype, device)
    _assert_kind(shell_offsets(verts, faces, ShellConfig(offset_mm=30.0, safe=True, repair_iterations=1)),
                 kind, dtype, device)
    _assert_kind(fold_distances(verts, faces), kind, dtype, device)
    _assert_kind(self_intersecting_faces(verts, faces), kind, dtype, device, floating=False)
    edges, counts, corner = mesh_edges(faces)
    for a in (edges, counts, corner):
        _assert_kind(a, kind, dtype, device, floating=False)
    np.testing.assert_allclose(np.asarray(torch.as_tensor(safe).cpu()), 30.0, rtol=1e-6)  # a sphere keeps d


# ------------------------------------------------------------------------------------ normal maps
@KINDS
@DTYPES
def test_normal_maps(sphere, kind, dtype, device):
    v, f, atlas = sphere
    table = uv_texel_table(atlas, 16)
    vn = vertex_normals(v, f)[None].repeat(3, 0)
    normals = _as(kind, vn, dtype, device)
    _assert_kind(normal_maps(normals, f, table), kind, dtype, device)
    gather = NormalMapGather.from_table(table, f).to(device)
    maps = gather.apply(normals)
    _assert_kind(maps, kind, dtype, device)
    _assert_kind(gather.apply(normals, dtype=torch.float16), kind, torch.float16, device)
    window = temporal_window(maps, _as(kind, np.array([0, 2]), dtype, device), 2)
    _assert_kind(window, kind, dtype, device)
    assert tuple(window.shape) == (2, 9, 16, 16)
    _assert_kind(rasterize_normal_map_naive(normals[:1], f, atlas, 8), kind, dtype, device)


# ------------------------------------------------------------------------------------ atlas, texel tables
def test_atlas_and_texel_tables_are_numpy_records(sphere, device):
    v, f, atlas = sphere
    uvs, face_uvs = torch.tensor(atlas.uvs, device=device), torch.tensor(atlas.face_uvs, device=device)
    from_tensors = UVAtlas(uvs, face_uvs)
    assert isinstance(from_tensors.uvs, np.ndarray) and from_tensors.uvs.dtype == np.float64
    assert isinstance(from_tensors.face_uvs, np.ndarray) and from_tensors.face_uvs.dtype == np.int64
    again = UVAtlas.from_mesh(torch.as_tensor(v), torch.as_tensor(f), uvs, face_uvs)
    np.testing.assert_array_equal(again.uvs, atlas.uvs)
    table = uv_texel_table(from_tensors, 8)
    assert isinstance(table, TexelTable)
    assert all(isinstance(a, np.ndarray) for a in (table.face, table.bary, table.covered, table.valid))
    assert isinstance(texel_centers_uv(4), np.ndarray)


# ------------------------------------------------------------------------------------ ray casting, rasterising
@pytest.mark.parametrize("dtype", FLOAT_DTYPES)
def test_uv_ray_casting_and_rasterising_take_tensors_and_give_numpy(sphere, dtype, device):
    v, f, atlas = sphere
    outer = offset_shell(v, f, 30.0)
    cam = ref.look_at([0, 0, 2500.0], [0.0, 0.0, 0.0], 32, 24, focal=40.0)
    expect = UVRaycaster(v, f, outer, atlas).cast_foreground(cam)
    t = lambda a: torch.as_tensor(a, device=device).to(dtype) if a.dtype.kind == "f" else torch.as_tensor(a, device=device)  # noqa: E731
    got = UVRaycaster(t(v), t(f), t(outer), atlas).cast_foreground(cam)
    assert isinstance(got, RaycastHits) and isinstance(got.uv_inner, np.ndarray)
    np.testing.assert_array_equal(got.pixels, expect.pixels)
    np.testing.assert_allclose(got.uv_outer, expect.uv_outer, atol=1e-4)
    shaded = UVRasterizer(t(v), t(f), t(outer), atlas, method="numpy").shaded_pixels(cam)
    assert isinstance(shaded, ShadedPixels) and isinstance(shaded.uv_inner, np.ndarray) and shaded.num_rays > 0


# ------------------------------------------------------------------------------------ sampling
@DTYPES
def test_sample_uv_is_torch_only(dtype, device, unchecked):
    maps = torch.rand(2, 4, 8, 8, dtype=dtype, device=device)
    index = torch.tensor([0, 1, 1], device=device)
    uv = torch.rand(3, 2, dtype=dtype, device=device)
    _assert_kind(sample_uv(maps, index, uv), "torch", dtype, device)
    with unchecked(), pytest.raises(TypeError, match="uv: expected a torch.Tensor"):
        sample_uv(maps, index, uv.cpu().numpy())


# ------------------------------------------------------------------------------------ SMPL maths
@DTYPES
def test_smpl_maths_is_torch_only_in_the_inputs_dtype(dtype, device):
    rng = np.random.default_rng(0)
    V, J, NB = 12, 24, 4
    parents = torch.tensor([-1] + [0] * (J - 1), device=device)
    t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    W = rng.random((V, J))
    verts, joints = smpl_lbs(t(rng.normal(size=(2, NB))), t(rng.normal(0, 0.1, (2, 72))), t(rng.normal(size=(V, 3))),
                             t(rng.normal(0, 0.01, (V, 3, NB))), t(rng.normal(0, 0.01, (207, V * 3))),
                             t(rng.random((J, V)) / V), parents, t(W / W.sum(1, keepdims=True)))
    _assert_kind(verts, "torch", dtype, device)
    _assert_kind(joints, "torch", dtype, device)
    _assert_kind(batch_rodrigues(t(rng.normal(size=(5, 3)))), "torch", dtype, device)


# ------------------------------------------------------------------------------------ mis-shaped calls
def _typechecked(fn) -> bool:
    """Whether the test run's jaxtyping import hook wrapped ``fn`` (``--jaxtyping-packages``)."""
    return hasattr(fn, "__wrapped__")


@pytest.mark.parametrize("call", ["offset_shell", "lbs", "vertex_normals"])
def test_mis_shaped_vertices_raise_an_error_naming_the_argument(sphere, call, unchecked):
    v, f, _ = sphere
    flat = v[:, :2]  # (V, 2) vertices
    calls = {"offset_shell": (offset_shell, lambda: offset_shell(flat, f, 30.0), "verts"),
             "lbs": (lbs, lambda: lbs(flat, np.ones((len(v), 1)), np.tile(np.eye(4), (1, 1, 1, 1))), "rest_verts"),
             "vertex_normals": (vertex_normals, lambda: vertex_normals(torch.as_tensor(flat), f), "verts")}
    fn, bad_call, name = calls[call]
    # the library's own check, what every caller gets: a ValueError naming the argument and the shapes
    with unchecked(), pytest.raises(ValueError, match=rf"^{name}: expected shape \(.*3\), got \({len(v)}, 2\)"):
        bad_call()
    if not _typechecked(fn):
        pytest.skip("the jaxtyping checks are off in this run (no --jaxtyping-packages)")
    # the test run's annotation check comes first: jaxtyping's TypeCheckError names the parameter
    with pytest.raises(TypeError, match=rf"parameter '{name}'") as err:
        bad_call()
    assert type(err.value).__name__ == "TypeCheckError" and "V 3" in str(err.value)
