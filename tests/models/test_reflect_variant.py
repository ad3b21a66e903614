"""Tests of the ``two_surface_reflect`` variant: the MLP encodes the view direction reflected about the normal."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from deliffas.models.deliffas import DeliffasModel, FrameFeatures
from deliffas.models.ray_query import RayQuery
from deliffas.models.variants import VariantSpec, get_variant
from deliffas.models.zoo import DEFAULT_UNET_LEVELS, PRESETS, REFLECTED, TEXTURED, get_config
from tests.models.test_deliffas import S, make_rays, tiny_config


def _normal_maps(normal: tuple[float, float, float], batch: int = 1) -> torch.Tensor:
    """(B, 9, S, S) temporal normal maps whose current frame is ``normal`` everywhere (earlier frames random)."""
    maps = torch.randn(batch, 9, S, S, generator=torch.Generator().manual_seed(1))
    maps[:, :3] = torch.tensor(normal).view(1, 3, 1, 1)
    return maps


def test_spec_and_zoo_entries():
    spec = get_variant("two_surface_reflect")
    assert spec.viewdir and spec.reflect_viewdir and spec.inner_from_outer
    assert dataclasses.replace(spec, name="two_surface", viewdir=False, reflect_viewdir=False) == get_variant("two_surface")
    with pytest.raises(ValueError, match="reflect_viewdir needs viewdir"):
        VariantSpec("x", reflect_viewdir=True)
    for preset in PRESETS:  # the same model with the reflected direction; at `small` a shallower U-Net
        reflected, textured = get_config(REFLECTED, preset), get_config(TEXTURED, preset)
        levels = DEFAULT_UNET_LEVELS if preset == "small" else textured.unet.levels
        assert reflected == dataclasses.replace(textured, variant="two_surface_reflect",
                                                unet=dataclasses.replace(textured.unet, levels=levels))


def test_encoded_direction_is_the_reflection():
    """With n = (0, 0, 2) (unnormalised) everywhere, d = (a, b, c) is encoded as (a, b, -c)."""
    torch.manual_seed(0)
    model = DeliffasModel(tiny_config("two_surface_reflect"))
    features = model.encode(_normal_maps((0.0, 0.0, 2.0)), _normal_maps((1.0, 0.0, 0.0)))
    assert features.normals is not None and features.normals.shape == (1, 3, S, S)
    rays = make_rays(50, 1, torch.Generator().manual_seed(2))
    encoded, _ = model.gather_inputs(features, RayQuery(**rays))
    mirrored = rays["viewdir"] * torch.tensor([1.0, 1.0, -1.0])
    width = model.pe_viewdir.out_dim
    torch.testing.assert_close(encoded[:, -width:], model.pe_viewdir(mirrored))
    plain = DeliffasModel(tiny_config("two_surface"))
    assert plain.encode(_normal_maps((0.0, 0.0, 1.0)), _normal_maps((1.0, 0.0, 0.0))).normals is None


def test_colour_depends_on_the_normal_and_gradients_flow():
    torch.manual_seed(0)
    model = DeliffasModel(tiny_config("two_surface_reflect"))
    rays = RayQuery(**make_rays(40, 1, torch.Generator().manual_seed(3)))
    outer = _normal_maps((1.0, 0.0, 0.0))
    up, side = (model.encode(_normal_maps(n), outer) for n in ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)))
    # the U-Nets see different maps too: compare with the normals swapped only
    swapped = FrameFeatures(inner=up.inner, outer=up.outer, normals=side.normals)
    assert not torch.allclose(model.shade(up, rays), model.shade(swapped, rays))
    model.shade(up, rays).sum().backward()
    assert model.mlp.hidden[0].weight.grad.abs().sum() > 0 and model.unet_outer.final.weight.grad is not None


def test_missing_normals_is_a_clear_error():
    model = DeliffasModel(tiny_config("two_surface_reflect"))
    features = model.encode(_normal_maps((0.0, 0.0, 1.0)), _normal_maps((1.0, 0.0, 0.0)))
    bare = dataclasses.replace(features, normals=None)
    with pytest.raises(ValueError, match="features.normals is None"):
        model.shade(bare, RayQuery(**make_rays(4, 1, torch.Generator().manual_seed(0))))
