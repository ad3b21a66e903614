"""Tests of deliffas.models.deliffas: variants, depth-peeling mask, chunking, overfitting."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from deliffas.models.deliffas import VARIANTS, DeliffasModel, FrameFeatures, ModelConfig
from deliffas.models.light_field import LightFieldMLPConfig
from deliffas.models.losses import l1_foreground
from deliffas.models.ray_query import RayQuery
from deliffas.models.unet import UNetConfig

S = 16


def tiny_config(variant: str, **kwargs) -> ModelConfig:
    base = dict(
        variant=variant,
        atlas_res=S,
        feature_channels=4,
        pe_freqs=3,
        viewdir_pe_freqs=2,
        unet=UNetConfig(in_channels=9, out_channels=4, base_channels=4, max_channels=8),
        mlp=LightFieldMLPConfig(depth=3, width=16, feature_layer=1),
    )
    base.update(kwargs)
    return ModelConfig(**base)


def make_rays(n: int, batch: int, gen: torch.Generator):
    return dict(
        batch_index=torch.randint(0, batch, (n,), generator=gen),
        uv_inner=torch.rand(n, 2, generator=gen),
        uv_outer=torch.rand(n, 2, generator=gen),
        viewdir=torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1),
    )


@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_shapes_and_gradients(variant, device):
    gen = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    model = DeliffasModel(tiny_config(variant)).to(device)
    normals = torch.randn(2, 9, S, S, generator=gen).to(device)
    features = model.encode(normals, normals.flip(-1))
    rays = {k: v.to(device) for k, v in make_rays(40, 2, gen).items()}
    rgb = model.shade(features, RayQuery(**rays))
    assert rgb.shape == (40, 3) and rgb.min() > 0 and rgb.max() < 1
    rgb.sum().backward()
    used = [model.unet_inner] + [m for m in (model.unet_inner_2, model.unet_outer) if m is not None]
    for net in used:
        assert net.final.weight.grad is not None and net.final.weight.grad.abs().sum() > 0
    assert model.mlp.hidden[0].weight.grad.abs().sum() > 0
    expected_unets = {"single_surface": 1, "single_surface_viewdir": 1, "single_surface_two_unet": 2, "two_surface": 2}
    assert len(used) == expected_unets[variant]
    expected_channels = 8 if variant == "single_surface_two_unet" else 4
    assert features.inner.shape == (2, expected_channels, S, S)
    assert (features.outer is not None) == (variant == "two_surface")


def test_mlp_inputs_per_variant():
    pe = 2 + 2 * 2 * 3
    dims = {v: (DeliffasModel(tiny_config(v)).mlp.in_dim, DeliffasModel(tiny_config(v)).mlp.feature_dim) for v in VARIANTS}
    assert dims["single_surface"] == (pe, 4)
    assert dims["single_surface_viewdir"] == (pe + 3 + 3 * 2 * 2, 4)
    assert dims["single_surface_two_unet"] == (pe, 8)
    assert dims["two_surface"] == (2 * pe, 8)


def test_two_unet_has_two_surface_capacity():
    two_unet = DeliffasModel(tiny_config("single_surface_two_unet"))
    two_surface = DeliffasModel(tiny_config("two_surface"))
    pe = 2 + 2 * 2 * 3
    # only the first MLP layer differs: one uv encoding instead of two
    assert two_surface.num_parameters() - two_unet.num_parameters() == pe * 16


def test_viewdir_matters_only_for_viewdir_variant():
    gen = torch.Generator().manual_seed(1)
    rays = make_rays(30, 1, gen)
    normals = torch.randn(1, 9, S, S, generator=gen)
    for variant, should_change in [("single_surface_viewdir", True), ("single_surface", False)]:
        model = DeliffasModel(tiny_config(variant)).eval()
        f = model.encode(normals)
        a = model.shade(f, RayQuery(**rays))
        b = model.shade(f, RayQuery(**{**rays, "viewdir": -rays["viewdir"]}))
        assert (not torch.allclose(a, b)) == should_change


def test_inner_from_outer_reads_outer_map():
    gen = torch.Generator().manual_seed(2)
    model = DeliffasModel(tiny_config("two_surface")).eval()
    normals = torch.randn(2, 9, S, S, generator=gen)
    f = model.encode(normals, torch.randn(2, 9, S, S, generator=gen))
    rays = make_rays(64, 2, gen)
    mask = torch.rand(64, generator=gen) < 0.4
    mixed = model.shade(f, RayQuery(**rays, inner_from_outer=mask))
    plain = model.shade(f, RayQuery(**rays))
    swapped = model.shade(FrameFeatures(inner=f.outer, outer=f.outer), RayQuery(**rays))
    torch.testing.assert_close(mixed[~mask], plain[~mask])
    torch.testing.assert_close(mixed[mask], swapped[mask])
    assert not torch.allclose(mixed[mask], plain[mask])
    all_outer = model.shade(f, RayQuery(**rays, inner_from_outer=torch.ones(64, dtype=torch.bool)))
    torch.testing.assert_close(all_outer, swapped)



def test_peeled_rays_give_the_outer_map_the_gradient_of_two_lookups():
    """The outer map is sampled once for the outer uvs and the peeled rays' exit uvs: its gradient
    equals that of two separate lookups (and the inner map's that of the unpeeled rays)."""
    from deliffas.geometry.sampling import sample_uv

    gen = torch.Generator().manual_seed(3)
    model = DeliffasModel(tiny_config("two_surface")).eval()
    rays = make_rays(64, 2, gen)
    for mask in (torch.rand(64, generator=gen) < 0.4, torch.ones(64, dtype=torch.bool)):
        maps = [torch.randn(2, 4, S, S, generator=gen, requires_grad=True) for _ in range(2)]
        weights = torch.randn(64, 8, generator=gen)
        feats = torch.cat(model._sample_peeled(FrameFeatures(inner=maps[0], outer=maps[1]), rays["batch_index"],
                                               rays["uv_outer"], rays["uv_inner"], mask), dim=-1)
        (feats * weights).sum().backward()
        ref = [m.detach().clone().requires_grad_(True) for m in maps]
        inner = torch.where(mask[:, None], sample_uv(ref[1], rays["batch_index"], rays["uv_inner"]),
                            sample_uv(ref[0], rays["batch_index"], rays["uv_inner"]))
        outer = sample_uv(ref[1], rays["batch_index"], rays["uv_outer"])
        torch.testing.assert_close(feats.detach(), torch.cat([outer, inner], dim=-1).detach())
        (torch.cat([outer, inner], dim=-1) * weights).sum().backward()
        for got, want in zip(maps, ref):  # every ray peeled: the inner map is not read at all
            torch.testing.assert_close(torch.zeros_like(got) if got.grad is None else got.grad, want.grad)


def test_inner_from_outer_rejected_without_outer_map(unchecked):
    model = DeliffasModel(tiny_config("single_surface"))
    f = model.encode(torch.randn(1, 9, S, S))
    rays = make_rays(5, 1, torch.Generator().manual_seed(0))
    mask = torch.zeros(5, dtype=torch.bool)
    model.shade(f, RayQuery(**rays, inner_from_outer=mask))  # all False is fine
    mask[2] = True
    with unchecked(), pytest.raises(ValueError, match="no outer feature map"):
        model.shade(f, RayQuery(**rays, inner_from_outer=mask))
    with unchecked(), pytest.raises(ValueError, match="bool"):
        model.shade(f, RayQuery(**rays, inner_from_outer=mask.float()))


def test_required_inputs():
    model = DeliffasModel(tiny_config("two_surface"))
    normals = torch.randn(1, 9, S, S)
    with pytest.raises(ValueError, match="normal_outer"):
        model.encode(normals)
    with pytest.raises(ValueError, match="normal_inner"):
        model.encode(torch.randn(1, 6, S, S), normals)
    f = model.encode(normals, normals)
    with pytest.raises(ValueError, match="uv_outer"):
        model.shade(f, RayQuery(torch.zeros(3, dtype=torch.long), torch.rand(3, 2)))
    viewdir_model = DeliffasModel(tiny_config("single_surface_viewdir"))
    with pytest.raises(ValueError, match="viewdir"):
        viewdir_model.shade(viewdir_model.encode(normals), RayQuery(torch.zeros(3, dtype=torch.long), torch.rand(3, 2)))


def test_chunked_equals_full():
    gen = torch.Generator().manual_seed(3)
    model = DeliffasModel(tiny_config("two_surface")).eval()
    f = model.encode(torch.randn(2, 9, S, S, generator=gen), torch.randn(2, 9, S, S, generator=gen))
    rays = make_rays(103, 2, gen)
    mask = torch.rand(103, generator=gen) < 0.3
    full = model.shade(f, RayQuery(**rays, inner_from_outer=mask))
    with torch.no_grad():
        chunked = model.shade_chunked(f, RayQuery(**rays, inner_from_outer=mask), chunk_size=10)
    assert chunked.shape == (103, 3)
    torch.testing.assert_close(chunked, full)
    with pytest.raises(ValueError, match="chunk_size"):
        model.shade_chunked(f, RayQuery(**rays), chunk_size=0)


def test_forward_is_encode_then_shade():
    gen = torch.Generator().manual_seed(4)
    model = DeliffasModel(tiny_config("two_surface")).eval()
    ni, no = torch.randn(1, 9, S, S, generator=gen), torch.randn(1, 9, S, S, generator=gen)
    rays = make_rays(12, 1, gen)
    torch.testing.assert_close(model(ni, no, RayQuery(**rays)), model.shade(model.encode(ni, no), RayQuery(**rays)))


def test_float64_inputs_flow_through():
    model = DeliffasModel(tiny_config("two_surface")).double()
    gen = torch.Generator().manual_seed(5)
    normals = torch.randn(1, 9, S, S, generator=gen, dtype=torch.float64)
    rays = {k: (v.double() if v.is_floating_point() else v) for k, v in make_rays(7, 1, gen).items()}
    assert model(normals, normals, RayQuery(**rays)).dtype == torch.float64


def test_config_defaults_and_validation():
    cfg = ModelConfig()
    assert cfg.variant == "two_surface" and cfg.atlas_res == 1024 and cfg.temporal_window == 2
    assert cfg.unet is not None and cfg.unet.in_channels == 9 and cfg.unet.out_channels == 32
    assert cfg.mlp.depth == 8 and cfg.mlp.width == 256 and cfg.pe_freqs == 10
    assert ModelConfig(temporal_window=0).unet.in_channels == 3
    with pytest.raises(ValueError, match="require 3"):
        ModelConfig(temporal_window=0, unet=UNetConfig(in_channels=9))
    with pytest.raises(ValueError, match="variant"):
        ModelConfig(variant="three_surface")  # type: ignore[arg-type]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.atlas_res = 8  # type: ignore[misc]


def test_accounting():
    model = DeliffasModel(tiny_config("two_surface"))
    assert model.num_parameters() == sum(p.numel() for p in model.parameters())
    model.unet_outer.requires_grad_(False)
    frozen = sum(p.numel() for p in model.unet_outer.parameters())
    assert model.num_parameters(trainable_only=True) == model.num_parameters() - frozen
    wide = DeliffasModel(tiny_config("two_surface", mlp=LightFieldMLPConfig(depth=3, width=32, feature_layer=1)))
    assert wide.flops_per_ray() > model.flops_per_ray() > model.mlp.flops_per_ray()


def test_tiny_two_surface_overfits_one_frame():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    cfg = tiny_config(
        "two_surface",
        atlas_res=32,
        feature_channels=8,
        pe_freqs=4,
        unet=UNetConfig(in_channels=9, out_channels=8, base_channels=8, max_channels=16),
        mlp=LightFieldMLPConfig(depth=3, width=64, feature_layer=1),
    )
    model = DeliffasModel(cfg)
    normal_inner = torch.nn.functional.normalize(torch.randn(1, 9, 32, 32, generator=gen), dim=1)
    normal_outer = torch.nn.functional.normalize(torch.randn(1, 9, 32, 32, generator=gen), dim=1)
    n = 1024
    uv_inner = torch.rand(n, 2, generator=gen)
    uv_outer = (uv_inner + 0.05 * torch.randn(n, 2, generator=gen)).clamp(0, 1)
    inner_from_outer = torch.rand(n, generator=gen) < 0.2
    u, v = uv_inner[:, 0:1], uv_inner[:, 1:2]
    phase = torch.tensor([0.0, 1.0, 2.0])
    target = 0.5 + 0.35 * torch.sin(2 * math.pi * u + phase) * torch.cos(2 * math.pi * v)  # (N, 3)
    batch_index = torch.zeros(n, dtype=torch.long)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        features = model.encode(normal_inner, normal_outer)
        rgb = model.shade(features, RayQuery(batch_index, uv_inner, uv_outer, inner_from_outer=inner_from_outer))
        loss = l1_foreground(rgb, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] / 5, (losses[0], losses[-1])


@pytest.mark.parametrize("variant", ["two_surface", "single_surface_two_unet"])
@pytest.mark.parametrize("batch", [1, 2])
def test_atlases_sampled_apart_give_the_joined_maps_values_and_gradients(variant, batch):
    """``encode(joined=False)`` (the training step) samples the texture atlases apart from the U-Net maps: the
    same MLP inputs and the same gradient of every parameter as the joined maps, peeled rays included."""
    gen = torch.Generator().manual_seed(5)
    torch.manual_seed(0)
    model = DeliffasModel(tiny_config(variant, texture_channels=3))
    with torch.no_grad():
        for t in model.texture_parameters():
            t.normal_(generator=gen)
    normals = torch.randn(batch, 9, S, S, generator=gen)
    rays = make_rays(50, batch, gen)
    peel = torch.rand(50, generator=gen) < 0.4
    query = RayQuery(**rays, inner_from_outer=peel if model.spec.inner_from_outer else None)
    weights = torch.randn(50, model.mlp.feature_dim, generator=gen)
    got = {}
    for joined in (True, False):
        model.zero_grad()
        features = model.encode(normals, normals.flip(-1), joined=joined)
        assert (features.inner_texture is None) == joined
        encoded, feats = model.gather_inputs(features, query)
        (feats * weights).sum().backward()
        got[joined] = feats.detach(), {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    torch.testing.assert_close(got[False][0], got[True][0])
    assert got[False][1].keys() == got[True][1].keys() and any("texture" in n for n in got[True][1])
    for name, grad in got[True][1].items():
        torch.testing.assert_close(got[False][1][name], grad, msg=name)


def test_atlases_finer_than_the_maps_stay_joined():
    """With ``texture_scale`` > 1 the U-Net maps are upsampled to the atlas side and joined to it either way."""
    model = DeliffasModel(tiny_config("two_surface", texture_channels=3, texture_scale=2))
    normals = torch.randn(1, 9, S, S)
    features = model.encode(normals, normals, joined=False)
    assert features.inner_texture is None and features.inner.shape == (1, 4 + 3, 2 * S, 2 * S)


def test_u_nets_below_the_atlas_side_keep_the_atlases_apart():
    """``unet_downsample`` 2: the U-Nets read the normal maps average-pooled to S / 2 and write S / 2 maps; the
    texture atlases keep side S and stay apart, joined or not; the normals for the reflection keep side S; gradients
    reach the U-Nets and the atlases; the factor must be a power of two dividing S."""
    model = DeliffasModel(tiny_config("two_surface_reflect", texture_channels=3, unet_downsample=2))
    normals = torch.randn(1, 9, S, S)
    for joined in (True, False):
        features = model.encode(normals, normals.flip(-1), joined=joined)
        assert features.inner.shape == (1, 4, S // 2, S // 2) and features.outer.shape == (1, 4, S // 2, S // 2)
        assert features.inner_texture.shape == (1, 3, S, S) and features.normals.shape[-1] == S
    reference = model.unet_inner(torch.nn.functional.avg_pool2d(normals, 2))
    torch.testing.assert_close(features.inner, reference.contiguous(memory_format=torch.channels_last))
    query = RayQuery(torch.zeros(5, dtype=torch.long), torch.rand(5, 2), torch.rand(5, 2),
                     torch.nn.functional.normalize(torch.randn(5, 3), dim=-1), torch.tensor([1, 0, 0, 1, 0]).bool())
    encoded, feats = model.gather_inputs(features, query)
    assert feats.shape == (5, 2 * (4 + 3))
    model.shade(features, query).sum().backward()
    assert model.texture_inner.grad is not None and model.unet_inner.down[0][0].weight.grad is not None
    for bad in (3, 32, 0):
        with pytest.raises(ValueError, match="unet_downsample"):
            tiny_config("two_surface", unet_downsample=bad)
