"""Tests of deliffas.models.vgg: torchvision key layout, file loading, seeded random weights."""

from __future__ import annotations

import math
import os

import pytest
import torch

from deliffas.models.vgg import (
    VGG16Features,
    PerceptualWeightsUnavailable,
    load_vgg16_weights,
    random_vgg16,
    read_state_dict,
    vgg16_state_dict_shapes,
)


def test_state_dict_keys_match_torchvision_layout(torchvision_vgg16_convs):
    expected = {}
    for idx, (c_out, c_in) in torchvision_vgg16_convs.items():
        expected[f"features.{idx}.weight"] = (c_out, c_in, 3, 3)
        expected[f"features.{idx}.bias"] = (c_out,)
    assert vgg16_state_dict_shapes() == expected
    ordered = [f"features.{i}.{p}" for i in sorted(torchvision_vgg16_convs) for p in ("weight", "bias")]
    assert list(VGG16Features().state_dict()) == ordered


def _assert_loaded(model: VGG16Features, state: dict[str, torch.Tensor]) -> None:
    for key, value in model.state_dict().items():
        assert torch.equal(value, state[key]), key
    assert all(not p.requires_grad for p in model.parameters())
    assert not model.training


@pytest.mark.parametrize("fmt", ["pth", "safetensors"])
def test_load_from_explicit_path(vgg_files, fmt, no_weights):
    model, record = load_vgg16_weights("vgg16-imagenet", path=vgg_files[fmt])
    _assert_loaded(model, vgg_files["state"])
    assert record.name == "vgg16-imagenet" and record.path == str(vgg_files[fmt]) and record.seed is None


def test_load_from_env_and_hub_cache(vgg_files, no_weights, monkeypatch):
    monkeypatch.setenv("DELIFFAS_VGG16_WEIGHTS", str(vgg_files["safetensors"]))
    _, record = load_vgg16_weights()
    assert record.path == str(vgg_files["safetensors"])
    monkeypatch.delenv("DELIFFAS_VGG16_WEIGHTS")
    hub = no_weights / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    os.symlink(vgg_files["pth"], hub / "vgg16-397923af.pth")
    model, record = load_vgg16_weights("vgg16-imagenet")
    assert record.path == str(hub / "vgg16-397923af.pth")
    _assert_loaded(model, vgg_files["state"])


def test_missing_imagenet_weights_raise_with_locations(no_weights, tmp_path, unchecked):
    with unchecked(), pytest.raises(PerceptualWeightsUnavailable) as info:
        load_vgg16_weights("vgg16-imagenet")
    message = str(info.value)
    assert str(no_weights / "hub" / "checkpoints" / "vgg16-397923af.pth") in message
    assert "--perceptual vgg16-random" in message
    with unchecked(), pytest.raises(PerceptualWeightsUnavailable, match="nowhere.pth"):
        load_vgg16_weights("vgg16-imagenet", path=tmp_path / "nowhere.pth")
    with unchecked(), pytest.raises(ValueError, match="source"):
        load_vgg16_weights("vgg19-imagenet")  # type: ignore[arg-type]


def test_wrong_shapes_and_unsafe_pickles_rejected(vgg_files, tmp_path):
    state = dict(vgg_files["state"])
    state["features.2.weight"] = torch.zeros(64, 64, 5, 5)
    bad = tmp_path / "bad.pth"
    torch.save(state, bad)
    with pytest.raises(ValueError, match=r"features\.2\.weight"):
        load_vgg16_weights(path=bad)
    evil = tmp_path / "evil.pth"
    torch.save({"features.0.weight": torch.zeros(1), "obj": _NotATensor()}, evil)
    with pytest.raises(ValueError, match="evil.pth"):
        read_state_dict(evil)


class _NotATensor:
    """A pickled object that ``weights_only=True`` must refuse."""


def test_random_backbone_is_seeded():
    a, rec_a = load_vgg16_weights("vgg16-random", seed=3)
    b, _ = load_vgg16_weights("vgg16-random", seed=3)
    c, _ = load_vgg16_weights("vgg16-random", seed=4)
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key]), key
    assert not torch.equal(a.features[0].weight, c.features[0].weight)
    assert rec_a.name == "vgg16-random" and rec_a.seed == 3 and rec_a.path is None
    conv = a.features[28]
    assert torch.count_nonzero(conv.bias) == 0
    expected_std = math.sqrt(2.0 / (512 * 9))
    assert abs(float(conv.weight.std()) - expected_std) < 0.02 * expected_std


def test_random_backbone_first_values_are_stable():
    # Pins the documented scheme: first conv weights = randn from a seed-0 CPU generator x sqrt(2 / (64 * 9)).
    gen = torch.Generator().manual_seed(0)
    expected = torch.randn(64, 3, 3, 3, generator=gen) * math.sqrt(2.0 / (64 * 9))
    assert torch.equal(random_vgg16(0).features[0].weight, expected)


def test_forward_layers(random_backbone):
    model, _ = random_backbone
    out = model(torch.rand(1, 3, 32, 32), ("relu1_2", "relu3_3"))
    assert set(out) == {"relu1_2", "relu3_3"}
    assert out["relu1_2"].shape == (1, 64, 32, 32) and out["relu3_3"].shape == (1, 256, 8, 8)
    with pytest.raises(ValueError, match="unknown layers"):
        model(torch.rand(1, 3, 32, 32), ("conv9_9",))
