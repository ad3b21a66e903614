"""recipes.quality_limits on a tiny capture: both bounds and the run's own score."""

from __future__ import annotations

import json
import math

import pytest


@pytest.mark.slow
def test_quality_limits_on_a_tiny_capture(tmp_path):
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture
    from deliffas.engine.train import TrainConfig, train
    from recipes import quality_limits

    base = dict(num_frames=4, num_test_frames=1, num_cameras=4, width=32, height=32, test_cameras=(3,), seed=0)
    for name, ss in (("point", 1), ("ss", 2)):
        synthesize_capture(tmp_path / name, SynthConfig(supersample=ss, **base))
        convert(tmp_path / name, tmp_path / f"{name}_shards", ConvertConfig(atlas_res=32, progress=False))
    train(TrainConfig(shards=str(tmp_path / "point_shards"), out=str(tmp_path / "run"), preset="tiny", iters=2,
                      cameras_per_frame=2, protocol="all", num_workers=0, validation_cameras=1, checkpoint_every=2,
                      preview_every=0, progress=False))
    out = quality_limits.main(["--out", str(tmp_path / "limits"), "--run", str(tmp_path / "run"),
                               "--supersampled-shards", str(tmp_path / "ss_shards"), "--sides", "32,64",
                               "--frames", "2"])
    ceiling = out["aliasing_ceiling"]
    assert ceiling["validation"]["images"] == 2 and ceiling["novel_view"]["images"] == 2
    assert 10 < ceiling["novel_view"]["masked_psnr"] < math.inf
    oracle = out["texture_oracle"]
    # fitted on the training cameras: it explains them better than cameras it never saw
    assert oracle["train"][32] > oracle["novel_view"][32] - 1.0
    assert 0 < oracle["coverage"][64] <= oracle["coverage"][32] <= 1
    assert "aliasing ceiling" in (tmp_path / "limits" / "results.md").read_text()
    assert json.loads((tmp_path / "limits" / "results.json").read_text())["frames"] == 2


def test_a_capture_that_is_not_the_runs_is_refused(tmp_path):
    pytest.importorskip("open3d")
    from deliffas.engine.quality_limits import aliasing_ceiling

    with pytest.raises((FileNotFoundError, ValueError)):
        aliasing_ceiling(tmp_path / "no_run", tmp_path / "no_shards")
