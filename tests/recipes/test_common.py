"""recipes.common: a recipe never reports an old run under a new configuration's name."""

from __future__ import annotations

import dataclasses
import json

import pytest

from deliffas.engine.train import TrainConfig
from recipes.common import check_same_configuration


def test_run_folder_of_another_configuration_is_refused(tmp_path):
    run = tmp_path / "run"
    cfg = TrainConfig(shards="s", out=str(run), model="single_surface_viewdir", preset="tiny", iters=8,
                      model_overrides={"unet": {"dropout": 0.1}})
    check_same_configuration(run, cfg)  # no run yet
    run.mkdir()
    (run / "train_config.json").write_text(json.dumps({"train": dataclasses.asdict(cfg)}, default=str))
    check_same_configuration(run, cfg)
    check_same_configuration(run, dataclasses.replace(cfg, iters=16, device="cpu", progress=False))  # continue it
    for change in ({"model_overrides": {"viewdir_pe_freqs": 0}}, {"perceptual": "vgg16-random"},
                   {"perceptual_mode": "patch"}, {"seed": 1}, {"shards": "other"}):
        with pytest.raises(SystemExit, match="holds a run trained with other settings") as err:
            check_same_configuration(run, dataclasses.replace(cfg, **change))
        assert next(iter(change)) in str(err.value)
