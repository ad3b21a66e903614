"""Tests of deliffas.models.zoo: registry, presets, config JSON round trip, checkpoints."""

from __future__ import annotations

import dataclasses

import json
import os

import pytest
import torch

from deliffas.models import zoo
from deliffas.models.deliffas import VARIANTS, DeliffasModel, ModelConfig
from deliffas.models.ray_query import RayQuery
from deliffas.models.light_field import LightFieldMLPConfig
from deliffas.models.unet import UNetConfig, resolve_levels
from deliffas.models.zoo import (
    CheckpointError,
    config_from_dict,
    config_to_dict,
    get_config,
    list_models,
    list_presets,
    load_checkpoint,
    register,
    save_checkpoint,
)
from deliffas.models.zoo import REFLECTED, TEXTURE_CHANNELS, TEXTURE_SCALE, TEXTURED


def test_registry_lists_variants_and_presets():
    from deliffas.models.model_table import MODEL_ROWS

    assert list_models() == sorted(r.name for r in MODEL_ROWS)  # a new row is listed with no test to edit
    assert {*VARIANTS, "two_surface_reflect", TEXTURED, REFLECTED} <= set(list_models())
    textured = get_config(TEXTURED)
    assert textured == dataclasses.replace(get_config("two_surface"), texture_channels=TEXTURE_CHANNELS,
                                           texture_scale=TEXTURE_SCALE)
    for name in VARIANTS:
        assert set(list_presets(name)) == {"paper", "small", "realtime", "tiny"}
        assert get_config(name).variant == name
        assert get_config(name) == get_config(name, "small")


def test_paper_small_tiny_sizes():
    paper = get_config("two_surface", "paper")
    assert paper.atlas_res == 1024 and resolve_levels(paper.unet, paper.atlas_res) == 10
    assert paper.unet.base_channels == 16 and paper.unet.max_channels == 512
    assert (paper.mlp.depth, paper.mlp.width, paper.mlp.feature_layer) == (8, 256, 4)
    assert paper.feature_channels == 32 and paper.pe_freqs == 10 and paper.temporal_window == 2
    small = get_config("two_surface", "small")
    assert small.atlas_res == 128 and small.mlp.width <= 64 and small.unet.max_channels <= 64
    assert get_config("single_surface", "tiny").atlas_res == 32


def test_unknown_names_and_duplicate_registration(monkeypatch, unchecked):
    with unchecked(), pytest.raises(KeyError, match="registered"):
        get_config("three_surface")
    with unchecked(), pytest.raises(KeyError, match="presets"):
        get_config("two_surface", "huge")
    monkeypatch.setattr(zoo, "_REGISTRY", dict(zoo._REGISTRY))
    cfg = ModelConfig(atlas_res=16)
    register("mine", {"tiny": cfg})
    assert get_config("mine", "tiny") is cfg and "mine" in list_models()
    with unchecked(), pytest.raises(ValueError, match="already registered"):
        register("mine", {"tiny": cfg})
    register("mine", {"x": cfg}, overwrite=True)
    assert list_presets("mine") == ["x"]
    with unchecked(), pytest.raises(ValueError, match="ModelConfig"):
        register("other", {"x": {"atlas_res": 16}})  # type: ignore[dict-item]


@pytest.mark.parametrize("name", VARIANTS)
@pytest.mark.parametrize("preset", ["paper", "small", "tiny"])
def test_config_json_round_trip(name, preset):
    cfg = get_config(name, preset)
    text = json.dumps(config_to_dict(cfg))
    back = config_from_dict(ModelConfig, json.loads(text))
    assert back == cfg
    assert isinstance(back.unet, UNetConfig) and isinstance(back.mlp, LightFieldMLPConfig)


def test_config_from_dict_rejects_unknown_and_invalid():
    data = config_to_dict(get_config("two_surface", "tiny"))
    with pytest.raises(ValueError, match="unknown keys"):
        config_from_dict(ModelConfig, {**data, "colour": 3})
    with pytest.raises(ValueError, match=r"config\.unet: unknown keys"):
        config_from_dict(ModelConfig, {**data, "unet": {**data["unet"], "depth": 3}})
    with pytest.raises(ValueError, match="variant"):
        config_from_dict(ModelConfig, {**data, "variant": "nope"})


def _trained_like_model() -> DeliffasModel:
    torch.manual_seed(0)
    model = DeliffasModel(get_config("two_surface", "tiny"))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    model.train()
    model.encode(torch.randn(2, 9, 32, 32), torch.randn(2, 9, 32, 32))  # moves BatchNorm running stats
    return model


def test_checkpoint_round_trip_is_bit_exact(tmp_path):
    model = _trained_like_model()
    out = save_checkpoint(tmp_path / "ckpt", model, extra={"step": 12, "perceptual": {"name": "vgg16-random"}})
    assert sorted(os.listdir(out)) == ["config.json", "weights.safetensors"]
    loaded = load_checkpoint(out)
    assert loaded.config == model.config and loaded.extra == {"step": 12, "perceptual": {"name": "vgg16-random"}}
    state, state2 = model.state_dict(), loaded.model.state_dict()
    assert state.keys() == state2.keys()
    for key in state:
        assert state[key].dtype == state2[key].dtype and torch.equal(state[key], state2[key]), key
    assert not loaded.model.training
    model.eval()
    gen = torch.Generator().manual_seed(1)
    normals = torch.randn(1, 9, 32, 32, generator=gen)
    bi, uv, uo = torch.zeros(20, dtype=torch.long), torch.rand(20, 2, generator=gen), torch.rand(20, 2, generator=gen)
    query = RayQuery(bi, uv, uo)
    assert torch.equal(model(normals, normals, query), loaded.model(normals, normals, query))


def test_channels_last_model_saves(tmp_path):
    model = _trained_like_model().to(memory_format=torch.channels_last)
    loaded = load_checkpoint(save_checkpoint(tmp_path / "cl", model))
    assert torch.equal(loaded.model.unet_inner.final.weight, model.unet_inner.final.weight)


def test_truncated_or_corrupted_files_raise(tmp_path):
    out = save_checkpoint(tmp_path / "ckpt", _trained_like_model())
    weights = out / "weights.safetensors"
    blob = weights.read_bytes()
    weights.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(CheckpointError, match=r"weights\.safetensors.*truncated"):
        load_checkpoint(out)
    flipped = bytearray(blob)
    flipped[-5] ^= 0xFF
    weights.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match=r"weights\.safetensors.*corrupted"):
        load_checkpoint(out)
    weights.write_bytes(blob)
    load_checkpoint(out)
    config = out / "config.json"
    text = config.read_text()
    config.write_text(text[: len(text) // 2])
    with pytest.raises(CheckpointError, match=r"config\.json"):
        load_checkpoint(out)
    with pytest.raises(CheckpointError, match="missing"):
        load_checkpoint(tmp_path / "nowhere")
    assert isinstance(CheckpointError("x"), ValueError)


def test_inconsistent_config_and_weights_raise(tmp_path):
    out = save_checkpoint(tmp_path / "ckpt", _trained_like_model())
    meta = json.loads((out / "config.json").read_text())
    meta["config"]["mlp"]["width"] = 48
    (out / "config.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="does not match"):
        load_checkpoint(out)


def test_failed_save_leaves_previous_checkpoint(tmp_path):
    model = _trained_like_model()
    out = save_checkpoint(tmp_path / "ckpt", model, extra={"step": 1})
    with pytest.raises(ValueError, match="JSON"):
        save_checkpoint(out, DeliffasModel(get_config("two_surface", "tiny")), extra={"bad": object()})
    assert load_checkpoint(out).extra == {"step": 1}
    assert sorted(os.listdir(out)) == ["config.json", "weights.safetensors"]
    with pytest.raises(ValueError, match="differs"):
        save_checkpoint(out, model, config=get_config("single_surface", "tiny"))


def test_model_table_is_the_zoo_and_the_docs():
    """The zoo registers exactly the table's models at the table's presets; docs/models.md shows the tables as
    generated; every built-in variant has a row; the default of ``deliffas train`` is the table's."""
    from pathlib import Path

    from deliffas.engine.train_config import TrainConfig
    from deliffas.models.deliffas import VARIANTS
    from deliffas.models.model_table import (DEFAULT_MODEL, MODEL_ROWS, PRESET_ROWS, model_table_markdown,
                                             preset_table_markdown)
    from deliffas.models.variants import EXTENSION_VARIANTS

    names = {r.name for r in MODEL_ROWS}
    assert names <= set(list_models()) and {*VARIANTS, *(v.name for v in EXTENSION_VARIANTS)} <= names
    assert all(list_presets(n) == [p.name for p in PRESET_ROWS] for n in names)
    assert TrainConfig.model == DEFAULT_MODEL and get_config(DEFAULT_MODEL, "small").unet.levels == 4
    docs = (Path(__file__).resolve().parents[2] / "docs" / "models.md").read_text(encoding="utf-8")
    assert model_table_markdown() in docs and preset_table_markdown() in docs, \
        "docs/models.md's tables are out of date: run python scripts/docs_tables.py"
