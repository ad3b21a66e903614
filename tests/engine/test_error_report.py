"""engine.error_report: a trained run's error budget, found as `eval` finds its shards."""

from __future__ import annotations

import shutil

import pytest


def test_the_budget_of_a_run_moved_together_with_its_shards(tiny_shards, tmp_path):
    from deliffas.engine.error_report import measure_error_budget
    from deliffas.engine.train import TrainConfig, train

    root = tmp_path / "a"
    shutil.copytree(tiny_shards, root / "shards")
    train(TrainConfig(shards=str(root / "shards"), out=str(root / "run"), preset="tiny", iters=2, cameras_per_frame=2,
                      protocol="all", num_workers=0, validation_cameras=1, checkpoint_every=2, preview_every=0,
                      progress=False))
    moved = tmp_path / "b"
    shutil.move(root, moved)
    budget = measure_error_budget(moved / "run", "validation", max_frames=2)
    assert budget["split"] == "validation" and budget["images"] == 2
    with pytest.raises(ValueError, match="split must be one of"):
        measure_error_budget(moved / "run", "validatoin")
