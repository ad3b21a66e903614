"""A tiny synthetic capture and small runs of the models the web player renders, shared by the web tests."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def web_capture(tmp_path_factory):
    """(subject folder, shards folder): 48 x 48 images, 4 cameras (3 held out), a 32 x 32 atlas, 3 test frames."""
    from example_data import tiny_capture

    return tiny_capture(tmp_path_factory.mktemp("web_capture"), num_test_frames=3)


@pytest.fixture(scope="session")
def web_runs(web_capture, tmp_path_factory):
    """``runs(model, preset, **overrides)``: a run of that model (its config's fields ``overrides`` replaced, e.g.
    ``unet_downsample=2``) trained for a few iterations on the capture (made once)."""
    from deliffas.engine.train import TrainConfig, train

    made: dict[tuple, Path] = {}
    root = tmp_path_factory.mktemp("web_runs")

    def runs(model: str, preset: str, **overrides) -> Path:
        key = (model, preset, *sorted(overrides.items()))
        if key not in made:
            run = root / "-".join([model, preset, *(f"{k}{v}" for k, v in sorted(overrides.items()))])
            train(TrainConfig(shards=str(web_capture[1]), out=str(run), model=model, preset=preset, iters=6,
                              cameras_per_frame=2, protocol="all", num_workers=0, checkpoint_every=6,
                              preview_every=0, log_every=1, progress=False, model_overrides=overrides))
            made[key] = run
        return made[key]

    return runs
