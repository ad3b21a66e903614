"""A variant registered outside deliffas trains through deliffas.engine with no engine change;
the resolved model config (preset, overrides, shards) reaches both the model and the data stream."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deliffas.engine.train import TrainConfig, train
from deliffas.models.variants import VariantSpec, register_variant, unregister_variant

TOY = VariantSpec("toy_viewdir_three_unets", inner_unets=3, viewdir=True)
"""Single surface, view direction, three inner U-Nets: not one of the paper's four."""


@pytest.fixture
def toy_variant():
    register_variant(TOY)
    yield TOY
    unregister_variant(TOY.name)


def _cfg(shards, out, **kw):
    base = dict(shards=str(shards), out=str(out), model="single_surface", preset="tiny", iters=2, cameras_per_frame=2,
                protocol="all", num_workers=0, checkpoint_every=2, preview_every=2, log_every=1, progress=False)
    base.update(kw)
    return TrainConfig(**base)


def test_toy_variant_trains_through_the_engine(tiny_shards, tmp_path, toy_variant):
    res = train(_cfg(tiny_shards, tmp_path / "run", model_overrides={"variant": toy_variant.name}))
    assert res.iterations == 2 and np.isfinite(res.last_loss)
    model = res.model
    assert model.spec is toy_variant and len(model.inner_unets()) == 3 and model.pe_viewdir is not None
    for net in model.inner_unets():
        assert net.final.weight.grad is not None and net.final.weight.grad.abs().sum() > 0
    record = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert record["model"]["variant"] == toy_variant.name


def test_temporal_window_override_reaches_model_and_data(tiny_shards, tmp_path, caplog):
    """TrainConfig(model_overrides={"temporal_window": 1}) trains T = 1 (it was silently 2: the data
    stream read the preset's window without the overrides)."""
    caplog.set_level("INFO", logger="deliffas.engine.train_config")
    run = tmp_path / "run"
    res = train(_cfg(tiny_shards, run, model="two_surface", iters=1, model_overrides={"temporal_window": 1}))
    assert res.model.config.temporal_window == 1
    assert res.model.unet_inner.config.in_channels == 6  # 3 (T + 1)
    record = json.loads((run / "train_config.json").read_text())
    assert record["data"]["temporal_window"] == 1 and record["model"]["temporal_window"] == 1
    steps = [r.getMessage() for r in caplog.records]
    assert any("zoo 'two_surface' preset 'tiny'" in m for m in steps)
    assert any("override temporal_window 2 -> 1" in m for m in steps)
