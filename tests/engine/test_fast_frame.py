"""fast.frame against the engine: the fast path renders what render_camera's plain path renders, its switches work."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from deliffas.fast import frame as fast_frame
from deliffas.engine.shading import render_camera
from deliffas.fast.frame import path_for_device
from deliffas.engine.rays import camera_rays, device_camera_rays
from deliffas.engine.shading import PLAIN
from deliffas.engine.timing import StageTimer
from deliffas.fast.config import RenderPathConfig
from deliffas.fast.shade import mlp_dtype
from deliffas.geometry.raycast import UVRaycaster
from deliffas.models import DeliffasModel, get_config


@pytest.fixture(scope="module")
def first_sample(tiny_shards):
    """The tiny capture's first evaluation sample and its shard info."""
    from deliffas.engine.data_bridge import evaluation_samples

    samples, info = evaluation_samples(str(tiny_shards), "all", max_frames=1, with_rays=False, protocol="all",
                                       temporal_window=2)
    return next(samples), info


@pytest.fixture(scope="module")
def frame(first_sample):
    sample, info = first_sample
    torch.manual_seed(0)
    cfg = dataclasses.replace(get_config("two_surface", "tiny"), atlas_res=info["atlas_res"])
    model = DeliffasModel(cfg).eval()
    with torch.no_grad():
        features = model.encode(*sample.normal_maps(torch.device("cpu")))
    raycaster = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
    return model, features, raycaster, sample.cameras


def _render(model, features, raycaster, cam, render_path):
    """``render_camera`` on the CPU by ``render_path`` (None: the plain path)."""
    return render_camera(model, features, raycaster, cam, torch.device("cpu"), StageTimer(torch.device("cpu")),
                         render_path=render_path if render_path is not None else PLAIN)


def test_fast_rays_equal_camera_rays(frame):
    _, _, raycaster, cameras = frame
    for cam in [*cameras, cameras[0].rescaled(97, 61)]:
        a, b = device_camera_rays(raycaster, cam, "cpu", "raster"), camera_rays(raycaster, cam)
        for name, tol in (("pixels", 0), ("inner_from_outer", 0), ("uv_inner", 1e-4), ("uv_outer", 1e-4),
                          ("viewdir", 1e-6)):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=tol, rtol=0, err_msg=name)


def _assert_fast_fp32_equals_plain(model, features, raycaster, cameras) -> None:
    """Every camera: the fast path in float32 renders the plain path's image (and the person covers > 50 px)."""
    for cam in cameras:
        plain = _render(model, features, raycaster, cam, None)
        fast = _render(model, features, raycaster, cam, RenderPathConfig(dtype="float32"))
        assert (plain.sum(-1) > 0).sum() > 50
        torch.testing.assert_close(fast, plain, atol=1e-4, rtol=0)


def test_fast_fp32_equals_plain(frame):
    model, features, raycaster, cameras = frame
    _assert_fast_fp32_equals_plain(model, features, raycaster, cameras)


def test_exact_encoding_equals_plain_and_the_table_is_within_its_error(frame):
    """``pe_table=False`` (the switch) is the exact fused pass, with and without projected features; the default
    table is within 1e-3 of it."""
    model, features, raycaster, cameras = frame
    plain = _render(model, features, raycaster, cameras[0], None)
    exact = _render(model, features, raycaster, cameras[0], RenderPathConfig(dtype="float32", pe_table=False))
    torch.testing.assert_close(exact, plain, atol=1e-4, rtol=0)
    sampled = _render(model, features, raycaster, cameras[0],
                      RenderPathConfig(dtype="float32", pe_table=False, project_features=False))
    torch.testing.assert_close(sampled, plain, atol=1e-4, rtol=0)
    tabled = _render(model, features, raycaster, cameras[0], RenderPathConfig(dtype="float32"))
    torch.testing.assert_close(tabled, exact, atol=1e-3, rtol=0)


def test_per_stage_path_equals_plain(frame):
    model, features, raycaster, cameras = frame
    plain = _render(model, features, raycaster, cameras[0], None)
    fast = _render(model, features, raycaster, cameras[0], RenderPathConfig(dtype="float32", fused=False))
    torch.testing.assert_close(fast, plain, atol=1e-4, rtol=0)


@pytest.mark.parametrize("fused", [False, True])  # True: bf16 hidden layers in the fused pass where native
def test_fast_bf16_within_its_precision(frame, fused):
    model, features, raycaster, cameras = frame
    plain = _render(model, features, raycaster, cameras[0], None)
    fast = _render(model, features, raycaster, cameras[0], RenderPathConfig(dtype="bfloat16", fused=fused))
    mse = float(((fast - plain) ** 2).mean())
    assert float((fast - plain).abs().max()) < 0.02 and -10 * np.log10(max(mse, 1e-20)) > 50


def test_ray_cast_fallback_and_unsupported_variant(frame, tiny_shards):
    model, features, raycaster, cameras = frame
    plain = _render(model, features, raycaster, cameras[0], None)
    for uv in ("raycast", "torch"):  # the fast path takes every uv source
        fast = _render(model, features, raycaster, cameras[0], RenderPathConfig(uv=uv, dtype="float32"))
        torch.testing.assert_close(fast, plain, atol=1e-5, rtol=0)
    two_unet = DeliffasModel(dataclasses.replace(model.config, variant="single_surface_two_unet")).eval()
    assert not fast_frame.supports(two_unet)  # the model's own gather_inputs and MLP
    with torch.no_grad():
        feats = two_unet.encode(features.inner.new_zeros(1, 9, *features.inner.shape[2:]))
    torch.testing.assert_close(_render(two_unet, feats, raycaster, cameras[0], RenderPathConfig(dtype="float32")),
                               _render(two_unet, feats, raycaster, cameras[0], None), atol=1e-4, rtol=0)


def test_switches(monkeypatch, unchecked):
    """The config reads no environment; the fast path is the CPU's (other devices render plain)."""
    assert path_for_device(RenderPathConfig(), "cpu") == RenderPathConfig()
    assert path_for_device(RenderPathConfig(uv="torch"), "meta") == RenderPathConfig(path="plain", uv="torch")
    assert path_for_device(PLAIN, "cpu") == PLAIN
    monkeypatch.setenv("DELIFFAS_RENDER_DTYPE", "half")  # the variable of earlier releases: not read
    assert mlp_dtype(RenderPathConfig().dtype) == mlp_dtype("auto")
    assert mlp_dtype("float32") == torch.float32 and mlp_dtype("bfloat16") == torch.bfloat16
    for bad, match in ((dict(dtype="fp8"), "dtype"), (dict(path="gpu"), "path"), (dict(uv="gpu"), "uv"),
                       (dict(in_flight=-1), "in_flight")):
        with unchecked(), pytest.raises(ValueError, match=match):
            RenderPathConfig(**bad)


def test_render_stream_equals_sequential(frame):
    model, features, raycaster, cameras = frame
    cams = [*cameras, cameras[0].rescaled(97, 61)] * 2

    def one(cam):
        return _render(model, features, raycaster, cam, RenderPathConfig())

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the stream's workers run on one intra-op thread each: compare like with like
    try:
        sequential = list(fast_frame.render_stream(one, cams, in_flight=1))
    finally:
        torch.set_num_threads(threads)
    pipelined = list(fast_frame.render_stream(one, cams, in_flight=2))
    assert torch.get_num_threads() == threads  # restored
    assert len(pipelined) == len(cams)
    for a, b in zip(sequential, pipelined):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="in_flight"):
        next(fast_frame.render_stream(one, cams, in_flight=0))


def test_frames_in_flight_switch(unchecked):
    assert RenderPathConfig(in_flight=3).frames_in_flight() == 3
    assert 1 <= RenderPathConfig().frames_in_flight() <= 2
    assert RenderPathConfig(path="plain", in_flight=3).frames_in_flight() == 1  # the plain path renders in sequence
    with unchecked(), pytest.raises(ValueError, match="in_flight"):
        RenderPathConfig(in_flight=-1)


def test_render_images_keeps_the_callers_fast_config(frame, monkeypatch):
    """Videos default to the fast path with project_features=False; a caller's config reaches the shader unchanged
    (the render once overrode it)."""
    import types

    import deliffas.engine.render as render

    model, _, raycaster, cameras = frame
    seen = []

    def spy(model, features, raycaster, camera, timer, fast, background):
        seen.append(fast)
        return torch.zeros(camera.height, camera.width, 3)

    monkeypatch.setattr(render, "fast_render_camera", spy)
    channels = 3 * (model.config.temporal_window + 1)
    maps = torch.zeros(channels, model.config.atlas_res, model.config.atlas_res)
    geometry = types.SimpleNamespace(inner=[raycaster.inner_verts], outer=[raycaster.outer_verts])
    assert render.RenderConfig(run="r", out="v.mp4").render_path == RenderPathConfig(project_features=False)
    for fast in (RenderPathConfig(project_features=True, in_flight=1),
                 RenderPathConfig(project_features=False, in_flight=1)):
        list(render.render_images(model, lambda i: (maps, maps), geometry, raycaster.faces, raycaster.atlas,
                                  cameras[:1], torch.device("cpu"), render_path=fast))
        assert seen[-1] == fast


def test_fast_path_renders_a_textured_model_as_the_plain_path(frame, tiny_shards):
    """A model with texture atlases (``ModelConfig.texture_channels``) has wider maps; the fast path takes them."""
    _, _, raycaster, cameras = frame
    torch.manual_seed(1)
    base = frame[0].config
    model = DeliffasModel(dataclasses.replace(base, texture_channels=3)).eval()
    with torch.no_grad():
        model.texture_inner.normal_()
        model.texture_outer.normal_()
    S, C = base.atlas_res, base.input_channels
    x = torch.rand(1, C, S, S) * 2 - 1
    with torch.no_grad():
        features = model.encode(x, x)
    _assert_fast_fp32_equals_plain(model, features, raycaster, cameras)


def test_fast_path_renders_a_finer_texture_as_the_plain_path(frame):
    _, _, raycaster, cameras = frame
    torch.manual_seed(2)
    base = frame[0].config
    model = DeliffasModel(dataclasses.replace(base, texture_channels=2, texture_scale=2)).eval()
    with torch.no_grad():
        model.texture_inner.normal_()
        model.texture_outer.normal_()
        x = torch.rand(1, base.input_channels, base.atlas_res, base.atlas_res) * 2 - 1
        features = model.encode(x, x)
    for cam in cameras[:2]:
        plain = _render(model, features, raycaster, cam, None)
        fast = _render(model, features, raycaster, cam, RenderPathConfig(dtype="float32"))
        torch.testing.assert_close(fast, plain, atol=1e-4, rtol=0)


@pytest.mark.parametrize("variant", ["two_surface_reflect", "two_surface_reflect_texture", "single_surface_viewdir"])
def test_fast_path_renders_a_view_direction_model_as_the_plain_path(frame, first_sample, variant):
    """Variants with a view direction (the reflected one, the training default's, the plain one) through the fast
    path: the rasteriser's view directions and, for the reflection, the frame's inner normal map. Every camera in fp32
    (fused, table and projected features); the exact and the per-stage paths; bf16 within its precision."""
    _, _, raycaster, cameras = frame
    torch.manual_seed(2)
    model = DeliffasModel(dataclasses.replace(get_config(variant, "tiny"), atlas_res=frame[0].config.atlas_res)).eval()
    with torch.no_grad():
        for p in [*model.mlp.parameters(), *model.texture_parameters()]:
            p.add_(0.3 * torch.randn_like(p))
        features = model.encode(*first_sample[0].normal_maps(torch.device("cpu")))
    assert fast_frame.supports(model)  # FastShader renders it, not the model's own gather_inputs
    _assert_fast_fp32_equals_plain(model, features, raycaster, cameras)
    plain = _render(model, features, raycaster, cameras[0], None)
    for fast in (RenderPathConfig(dtype="float32", pe_table=False, project_features=False),
                 RenderPathConfig(dtype="float32", fused=False)):
        torch.testing.assert_close(_render(model, features, raycaster, cameras[0], fast), plain, atol=1e-4, rtol=0)
    bf16 = _render(model, features, raycaster, cameras[0], RenderPathConfig(dtype="bfloat16"))
    mse = float(((bf16 - plain) ** 2).mean())
    assert float((bf16 - plain).abs().max()) < 0.02 and -10 * np.log10(max(mse, 1e-20)) > 50
