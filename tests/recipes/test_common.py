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


def test_full_recipe_captures_are_supersampled_and_the_flag_changes_it():
    from recipes.common import FULL_SUPERSAMPLE, recipe_parser, sizes_from_args

    p = recipe_parser("t")
    assert sizes_from_args(p.parse_args(["--out", "o"])).supersample == FULL_SUPERSAMPLE == 3
    assert sizes_from_args(p.parse_args(["--out", "o", "--quick"])).supersample == 1
    assert sizes_from_args(p.parse_args(["--out", "o", "--supersample", "2", "--size", "64"])).supersample == 2
    with pytest.raises(SystemExit, match="--supersample must be >= 1"):
        sizes_from_args(p.parse_args(["--out", "o", "--supersample", "0"]))


def test_a_capture_made_with_other_sizes_is_refused(tmp_path):
    from recipes.common import RecipeSizes, prepare_capture

    sizes = dataclasses.replace(RecipeSizes.quick(), frames=2, cameras=2, size=16)
    subject = tmp_path / "subject"
    subject.mkdir()
    made = {"num_frames": 2, "num_cameras": 2, "width": 16, "height": 16}  # an older synth.json: no supersample
    (subject / "synth.json").write_text(json.dumps({"config": made}))
    assert prepare_capture(tmp_path, sizes, jobs=1) == subject  # made earlier with these sizes: reused
    with pytest.raises(SystemExit, match=r"^error: .* made with other sizes \(supersample: 1 there, 3 now\)"):
        prepare_capture(tmp_path, dataclasses.replace(sizes, supersample=3), jobs=1)
    with pytest.raises(SystemExit, match=r"\(height: 16 there, 32 now; num_frames: 2 there, 4 now; "
                                         r"width: 16 there, 32 now\)"):
        prepare_capture(tmp_path, dataclasses.replace(sizes, frames=4, size=32), jobs=1)
