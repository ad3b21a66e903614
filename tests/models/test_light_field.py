"""Tests of deliffas.models.light_field."""

from __future__ import annotations

import pytest
import torch

from deliffas.models.light_field import LightFieldMLP, LightFieldMLPConfig


def test_shape_range_gradients(device):
    mlp = LightFieldMLP(LightFieldMLPConfig(depth=4, width=32, feature_layer=2), in_dim=10, feature_dim=6).to(device)
    enc = torch.randn(50, 10, device=device, requires_grad=True)
    feats = torch.rand(50, 6, device=device, requires_grad=True)
    rgb = mlp(enc, feats)
    assert rgb.shape == (50, 3)
    assert rgb.min() > 0 and rgb.max() < 1
    rgb.sum().backward()
    assert enc.grad.abs().sum() > 0 and feats.grad.abs().sum() > 0


def test_features_enter_after_feature_layer():
    cfg = LightFieldMLPConfig(depth=8, width=256, feature_layer=4)
    mlp = LightFieldMLP(cfg, in_dim=84, feature_dim=64)
    assert len(mlp.hidden) == 8
    assert [layer.in_features for layer in mlp.hidden] == [84, 256, 256, 256, 256, 256 + 64, 256, 256]
    assert mlp.output.in_features == 256 and mlp.output.out_features == 3
    last = LightFieldMLP(LightFieldMLPConfig(depth=2, width=8, feature_layer=1), 4, 5)
    assert last.output.in_features == 13


def test_features_change_output():
    torch.manual_seed(0)
    mlp = LightFieldMLP(LightFieldMLPConfig(depth=3, width=16, feature_layer=1), 4, 3)
    enc = torch.randn(20, 4)
    assert not torch.allclose(mlp(enc, torch.zeros(20, 3)), mlp(enc, torch.ones(20, 3)))


def test_flops_and_checks():
    mlp = LightFieldMLP(LightFieldMLPConfig(depth=2, width=8, feature_layer=0), in_dim=4, feature_dim=2)
    # layers 4->8, (8+2)->8, 8->3: 2*MACs + biases, + 2*8 ReLUs
    assert mlp.flops_per_ray() == (2 * 32 + 8) + (2 * 80 + 8) + (2 * 24 + 3) + 16
    with pytest.raises(ValueError, match="feature_layer"):
        LightFieldMLPConfig(depth=4, feature_layer=4)
    with pytest.raises(ValueError, match="features"):
        mlp(torch.randn(3, 4), torch.randn(3, 3))
    with pytest.raises(ValueError, match="encoded"):
        mlp(torch.randn(3, 5), torch.randn(3, 2))


@pytest.mark.parametrize("feature_layer", [0, 2, 3])
def test_features_enter_without_a_concatenation_as_with_one(feature_layer):
    """The layer after ``feature_layer`` multiplies its weight's column blocks with the features and the
    activations separately: the same output and gradients as Linear(cat([features, h]))."""
    torch.manual_seed(0)
    mlp = LightFieldMLP(LightFieldMLPConfig(depth=4, width=16, feature_layer=feature_layer), 6, 5)
    for p in mlp.parameters():  # non-zero biases, so the bias is counted once
        torch.nn.init.normal_(p, std=0.3)
    enc, feats = torch.randn(50, 6, requires_grad=True), torch.randn(50, 5, requires_grad=True)

    def with_cat(encoded, features):
        h = encoded
        for i, layer in enumerate(mlp.hidden):
            h = torch.relu(layer(h))
            if i == feature_layer:
                h = torch.cat([features, h], dim=-1)
        return torch.sigmoid(mlp.output(h))

    grads = []
    for f in (mlp, with_cat):
        mlp.zero_grad()
        enc.grad = feats.grad = None
        out = f(enc, feats)
        out.square().sum().backward()
        grads.append([out.detach(), enc.grad, feats.grad, *[p.grad.clone() for p in mlp.parameters()]])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
