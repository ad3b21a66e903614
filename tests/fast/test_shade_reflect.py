"""FastShader on variants with a view direction (``two_surface_reflect``, ``single_surface_viewdir``) equals
DeliffasModel.shade on every path: per-stage, fused fp32 (exact, with the encoding table, with projected features),
bf16 within its precision, the torch fallback; peeled rays reflect about the inner normal map as the model does."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import deliffas.fast.shade as fast_shade
from deliffas.fast.shade import FastShader, supports
from deliffas.models import DeliffasModel, get_config
from deliffas.models.deliffas import FrameFeatures
from deliffas.models.ray_query import RayQuery
from deliffas.native import LazyLibrary
from tests.fast.test_shade import _fused_built_with

CASES = [("two_surface_reflect", "tiny"), ("two_surface_reflect", "realtime"), ("two_surface_reflect", "small"),
         ("two_surface_reflect_texture", "realtime"), ("single_surface_viewdir", "tiny")]


def _case(name: str, preset: str, n: int = 1000 + 7, seed: int = 0, texture_scale: int = 1, peel: float = 0.2,
          unet_downsample: int = 1):
    """A model (random MLP biases and texture atlases), one frame's features encoded from random normal maps (unit
    normals per texel), and n rays: unit view directions, inner uvs a few outside [0, 1], ``peel`` of them peeled."""
    torch.manual_seed(seed)
    config = dataclasses.replace(get_config(name, preset), texture_scale=texture_scale, unet_downsample=unet_downsample)
    model = DeliffasModel(config).eval()
    with torch.no_grad():
        for p in [*model.mlp.parameters(), *model.texture_parameters()]:  # non-zero biases, textures
            p.add_(0.05 * torch.randn_like(p))
    cfg, g = model.config, torch.Generator().manual_seed(seed)
    maps = torch.randn(2, cfg.input_channels, cfg.atlas_res, cfg.atlas_res, generator=g)
    maps = maps / maps.view(2, -1, 3, cfg.atlas_res, cfg.atlas_res).norm(dim=2).repeat_interleave(3, 1)
    with torch.no_grad():
        feats = model.encode(maps[:1], maps[1:] if model.spec.outer_unet else None)
    viewdir = torch.randn(n, 3, generator=g)
    viewdir = viewdir / viewdir.norm(dim=-1, keepdim=True)
    uv_in = torch.rand(n, 2, generator=g) * 1.1 - 0.05
    uv_out = torch.rand(n, 2, generator=g)
    peeled = (torch.rand(n, generator=g) < peel) if model.spec.inner_from_outer else None
    query = RayQuery(torch.zeros(n, dtype=torch.long), uv_in, uv_out if model.spec.uses_uv_outer else None, viewdir,
                     peeled)
    return model, feats, query


def _fused(shader: FastShader) -> None:
    if not shader.fused_available():
        pytest.skip(f"the fused kernel is not built here: {fast_shade._FUSED.load().reason}")


def _within_bf16(got: torch.Tensor, ref: torch.Tensor) -> None:
    mse = float(((got - ref) ** 2).mean())
    assert float((got - ref).abs().max()) < 0.02 and -10 * torch.log10(torch.tensor(mse)) > 50


def test_supported_variants():
    for name in ("two_surface_reflect", "two_surface_reflect_texture", "single_surface_viewdir", "two_surface"):
        assert supports(DeliffasModel(get_config(name, "tiny")))
    assert not supports(DeliffasModel(get_config("single_surface_two_unet", "tiny")))


@pytest.mark.parametrize("name,preset", CASES)
def test_per_stage_inputs_and_colours_equal_shade(name, preset):
    """The C pass's operands equal ``gather_inputs``: uv encodings and features within 2e-6; the encoded direction
    within 3e-5 (the reflection's few-ulp rounding, as torch's own, times the highest frequency 2^(L-1) pi); the
    colours within 2e-6."""
    model, feats, query = _case(name, preset)
    shader = FastShader(model, fused=False)
    width = model.pe_viewdir.out_dim
    with torch.no_grad():
        ref_enc, ref_feats = model.gather_inputs(feats, query)
        enc, fts = shader.inputs(feats, query)
        torch.testing.assert_close(enc[:, :-width], ref_enc[:, :-width], atol=2e-6, rtol=0)
        torch.testing.assert_close(enc[:, -width:], ref_enc[:, -width:], atol=3e-5, rtol=0)
        torch.testing.assert_close(fts, ref_feats, atol=2e-6, rtol=0)
        torch.testing.assert_close(shader.shade_fused(feats, query), model.shade(feats, query), atol=2e-6, rtol=0)


@pytest.mark.parametrize("name,preset", CASES)
def test_fused_pass_equals_shade(name, preset):
    """The exact fused fp32 pass, into a canvas too; the table within its interpolation error of it; projected
    features within 2e-6 of sampled ones (with and without the table)."""
    model, feats, query = _case(name, preset)
    exact = FastShader(model)
    _fused(exact)
    with torch.no_grad():
        ref = model.shade(feats, query)
        got = exact.shade_fused(feats, query)
        torch.testing.assert_close(got, ref, atol=2e-6, rtol=0)
        rows = torch.randperm(len(ref))
        canvas = torch.zeros(len(ref), 3)
        exact.shade_fused(feats, query, out=canvas, rows=rows)
        torch.testing.assert_close(canvas[rows], ref, atol=2e-6, rtol=0)
        projected = FastShader(model, project_features=True).shade_fused(feats, query)
        torch.testing.assert_close(projected, got, atol=2e-6, rtol=0)
        table = FastShader(model, pe_table=True)
        assert table.encoding_table() is not None
        tabled = table.shade_fused(feats, query)
        err = (tabled - got).abs()
        assert float(err.max()) < 2e-3 and -10 * torch.log10((err**2).mean()) > 70
        both = FastShader(model, pe_table=True, project_features=True).shade_fused(feats, query)
        torch.testing.assert_close(both, tabled, atol=2e-6, rtol=0)


@pytest.mark.parametrize("name,preset", [("two_surface_reflect", "realtime"), ("two_surface_reflect_texture", "small"),
                                         ("single_surface_viewdir", "tiny")])
def test_bf16_within_its_precision(name, preset):
    """The per-stage bf16 operands and the fused pass of a bf16 shader (bf16 hidden layers where native, else fp32)."""
    model, feats, query = _case(name, preset)
    with torch.no_grad():
        ref = model.shade(feats, query)
        _within_bf16(FastShader(model, torch.bfloat16, fused=False).shade_fused(feats, query), ref)
        shader = FastShader(model, torch.bfloat16, pe_table=True, project_features=True)
        got = shader.shade_fused(feats, query)
        _within_bf16(got, ref)
        if shader.fused_bf16():  # the table and the projected maps serve the fp32 pass only
            torch.testing.assert_close(got, FastShader(model, torch.bfloat16).shade_fused(feats, query), atol=0, rtol=0)


def test_peeled_rays_reflect_about_the_inner_normals():
    """Every ray peeled: its feature comes from the outer map, its normal from the inner normal map, at the exit uv
    (as ``gather_inputs``); the normals matter (other normals, other colours)."""
    model, feats, query = _case("two_surface_reflect", "realtime", peel=1.0)
    assert bool(query.inner_from_outer.all())
    flipped = dataclasses.replace(feats, normals=feats.normals.flip(2).contiguous(memory_format=torch.channels_last))
    with torch.no_grad():
        for features in (feats, flipped):
            ref = model.shade(features, query)
            torch.testing.assert_close(FastShader(model, fused=False).shade_fused(features, query), ref, atol=2e-6,
                                       rtol=0)
            torch.testing.assert_close(FastShader(model).shade_fused(features, query), ref, atol=2e-6, rtol=0)
        assert float((model.shade(feats, query) - model.shade(flipped, query)).abs().max()) > 1e-3


def test_texture_atlases_finer_than_the_normal_maps():
    """``texture_scale`` 2: the feature maps have twice the normal map's side; the normals are sampled on their own."""
    model, feats, query = _case("two_surface_reflect_texture", "tiny", texture_scale=2)
    assert feats.inner.shape[-1] == 2 * feats.normals.shape[-1]
    with torch.no_grad():
        ref = model.shade(feats, query)
        torch.testing.assert_close(FastShader(model, fused=False).shade_fused(feats, query), ref, atol=2e-6, rtol=0)
        torch.testing.assert_close(FastShader(model).shade_fused(feats, query), ref, atol=2e-6, rtol=0)


@pytest.mark.parametrize("preset,peel", [("tiny", 0.2), ("realtime", 0.2), ("realtime", 1.0)])
def test_u_nets_at_half_the_atlas_side(preset, peel):
    """``unet_downsample`` 2: feature maps at half the side, the texture atlases apart at theirs, sampled apart by the
    fused pass (exact, with the table; projection declined) as by the model; the per-stage path and bf16 too."""
    model, feats, query = _case("two_surface_reflect_texture", preset, peel=peel, unet_downsample=2)
    assert feats.inner.shape[-1] * 2 == feats.inner_texture.shape[-1] == feats.normals.shape[-1]
    assert feats.outer_texture is not None and feats.inner.shape[1] == model.config.feature_channels
    with torch.no_grad():
        ref = model.shade(feats, query)
        torch.testing.assert_close(FastShader(model, fused=False).shade_fused(feats, query), ref, atol=2e-6, rtol=0)
        exact = FastShader(model, project_features=True)
        _fused(exact)
        assert exact.projected_maps(feats) is None
        torch.testing.assert_close(exact.shade_fused(feats, query), ref, atol=2e-6, rtol=0)
        tabled = FastShader(model, pe_table=True).shade_fused(feats, query)
        assert float((tabled - ref).abs().max()) < 2e-3
        _within_bf16(FastShader(model, torch.bfloat16).shade_fused(feats, query), ref)
        flip = lambda t: t.flip(2).contiguous(memory_format=torch.channels_last)  # noqa: E731
        without = dataclasses.replace(feats, inner_texture=flip(feats.inner_texture))  # the atlases matter
        if peel == 1.0:  # (every inner sample reads the outer atlas)
            without = dataclasses.replace(without, outer_texture=flip(feats.outer_texture))
        assert float((model.shade(without, query) - ref).abs().max()) > 1e-3
        torch.testing.assert_close(exact.shade_fused(without, query), model.shade(without, query), atol=2e-6, rtol=0)


def test_fused_pass_in_eight_ray_tiles(monkeypatch):
    """The engine's fused pass (table, projected features) in the 8-ray tiles of CPUs without AVX-512."""
    _fused_built_with("-mno-avx512f", monkeypatch)
    for downsample in (1, 2):  # the atlases in the maps, and apart
        model, feats, query = _case("two_surface_reflect_texture", "realtime", n=500, unet_downsample=downsample)
        with torch.no_grad():
            ref = model.shade(feats, query)
            torch.testing.assert_close(FastShader(model).shade_fused(feats, query), ref, atol=2e-6, rtol=0)
            got = FastShader(model, pe_table=True, project_features=True).shade_fused(feats, query)
        assert float((got - ref).abs().max()) < 2e-3


def test_fallback_without_the_kernels(monkeypatch):
    monkeypatch.setenv("DELIFFAS_NATIVE", "0")
    monkeypatch.setattr(fast_shade, "_KERNEL", LazyLibrary("ray_inputs", fast_shade._KERNEL.source, fallback="torch"))
    monkeypatch.setattr(fast_shade, "_FUSED", LazyLibrary("fused_shade", fast_shade._FUSED.source, fallback="torch"))
    model, feats, query = _case("two_surface_reflect", "tiny")
    with torch.no_grad():
        shader = FastShader(model, pe_table=True, project_features=True)
        assert not shader.fused_available()
        torch.testing.assert_close(shader.shade_fused(feats, query), model.shade(feats, query), atol=2e-6, rtol=0)


def test_missing_direction_or_normals_are_clear_errors():
    model, feats, query = _case("two_surface_reflect", "tiny", n=20)
    shader = FastShader(model)
    with torch.no_grad(), pytest.raises(ValueError, match="features.normals is None"):
        shader.shade_fused(dataclasses.replace(feats, normals=None), query)
    with torch.no_grad(), pytest.raises(ValueError, match="viewdir is required"):
        shader.shade_fused(feats, dataclasses.replace(query, viewdir=None))


def test_bf16_normal_maps_take_the_plain_inputs():
    """Normal maps the C passes cannot read (bf16) fall back to ``gather_inputs``."""
    model, feats, query = _case("two_surface_reflect", "tiny")
    half = FrameFeatures(inner=feats.inner, outer=feats.outer, normals=feats.normals.to(torch.bfloat16))
    with torch.no_grad():
        torch.testing.assert_close(FastShader(model).shade_fused(half, query), model.shade(half, query), atol=2e-6,
                                   rtol=0)
