"""ModelConfig.texture_channels: learnable per-texel feature atlases appended to the U-Nets' maps."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from deliffas.models import DeliffasModel, get_config
from deliffas.models.ray_query import RayQuery


def _model(variant: str, channels: int) -> DeliffasModel:
    torch.manual_seed(0)
    return DeliffasModel(dataclasses.replace(get_config(variant, "tiny"), texture_channels=channels))


@pytest.mark.parametrize("variant", ["two_surface", "single_surface", "single_surface_two_unet"])
def test_texture_channels_widen_every_sampled_map(variant):
    plain, textured = _model(variant, 0), _model(variant, 3)
    maps = 1 + int(plain.spec.outer_unet)
    assert textured.mlp.feature_dim == plain.mlp.feature_dim + 3 * maps
    S, C = plain.config.atlas_res, plain.config.input_channels
    x = torch.rand(2, C, S, S)
    feats = textured.encode(x, x if plain.spec.outer_unet else None)
    assert feats.inner.shape[1] == plain.encode(x, x if plain.spec.outer_unet else None).inner.shape[1] + 3
    assert feats.batch_size == 2
    if plain.spec.outer_unet:
        assert feats.outer.shape[1] == feats.inner.shape[1]  # depth peeling reads either map


def test_texture_is_learned_where_rays_sample_it():
    model = _model("two_surface", 2)
    S, C = model.config.atlas_res, model.config.input_channels
    x = torch.rand(1, C, S, S)
    n = 64
    query = RayQuery(batch_index=torch.zeros(n, dtype=torch.long), uv_inner=torch.rand(n, 2), uv_outer=torch.rand(n, 2),
                     inner_from_outer=torch.zeros(n, dtype=torch.bool))
    model(x, x, query).sum().backward()
    assert model.texture_inner.grad is not None and model.texture_inner.grad.abs().sum() > 0
    assert model.texture_outer.grad is not None and model.texture_outer.grad.abs().sum() > 0


def test_texture_channels_must_not_be_negative():
    with pytest.raises(ValueError, match="texture_channels"):
        dataclasses.replace(get_config("two_surface", "tiny"), texture_channels=-1)


def test_a_finer_texture_upsamples_the_unet_maps_to_its_side():
    cfg = get_config("two_surface", "tiny")
    model = DeliffasModel(dataclasses.replace(cfg, texture_channels=2, texture_scale=2))
    S, C = cfg.atlas_res, cfg.input_channels
    x = torch.rand(1, C, S, S)
    feats = model.encode(x, x)
    assert feats.inner.shape[-2:] == (2 * S, 2 * S) and feats.outer.shape[-2:] == (2 * S, 2 * S)
    with pytest.raises(ValueError, match="texture_scale"):
        dataclasses.replace(cfg, texture_channels=2, texture_scale=0)


def test_texture_atlases_get_their_own_learning_rate(tmp_path):
    from deliffas.engine.train import make_optimizer
    from deliffas.engine.train_config import TrainConfig

    model = _model("two_surface", 2)
    opt = make_optimizer(model, TrainConfig(shards="s", out="o", texture_lr_scale=10.0))
    assert [g["lr_scale"] for g in opt.param_groups] == [1.0, 10.0]
    assert opt.param_groups[1]["params"] == model.texture_parameters()
    assert sum(p.numel() for g in opt.param_groups for p in g["params"]) == model.num_parameters()
    assert len(make_optimizer(_model("two_surface", 0), TrainConfig(shards="s", out="o")).param_groups) == 1


def test_textured_maps_are_concatenated_in_channels_last():
    """The U-Net maps and the texture come out of the concatenation in channels_last (no second copy in
    encode), from either layout of the maps; the same values, and the texture gets its gradient."""
    maps = torch.rand(1, 4, 8, 8)
    texture = torch.rand(1, 2, 8, 8, requires_grad=True)
    ref = torch.cat([maps, texture.detach()], dim=1)
    for layout in (torch.channels_last, torch.contiguous_format):
        got = DeliffasModel._with_texture([maps.contiguous(memory_format=layout)], texture)
        assert got.is_contiguous(memory_format=torch.channels_last) and torch.equal(got, ref)
    (grad,) = torch.autograd.grad(got[:, 4:].sum(), texture)
    assert torch.equal(grad, torch.ones_like(texture))
