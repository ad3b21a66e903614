"""Honest evaluation: the foreground block beside the official numbers, the validation split, the frames
protocol stated, the few-images warning and the comparison grid, on a 30-iteration model."""

from __future__ import annotations

import json

import cv2
import pytest

from deliffas.cli import main as cli_main
from deliffas.engine.data_bridge import resolve_protocol, validation_cameras
from deliffas.engine.evaluate import MIN_IMAGES_WARNING, EvalConfig, evaluate
from deliffas.engine.figures import MIN_PANEL_PX
from deliffas.engine.train import TrainConfig, train


@pytest.fixture(scope="module")
def run30(tiny_shards, tmp_path_factory):
    """two_surface, tiny preset, 30 iterations, one training camera held out for validation, protocol auto."""
    run = tmp_path_factory.mktemp("honest") / "run"
    train(TrainConfig(shards=str(tiny_shards), out=str(run), model="two_surface", preset="tiny", iters=30,
                      cameras_per_frame=2, validation_cameras=1, num_workers=0, checkpoint_every=30,
                      preview_every=0, progress=False))
    return run


def test_foreground_block_and_margin_on_a_30_iteration_model(run30, tmp_path):
    grid = tmp_path / "grid.png"
    ev = evaluate(EvalConfig(run=str(run30), split="novel_view", grid=str(grid)))
    fg, official = ev.foreground, ev.official
    assert fg.protocol.startswith("foreground") and official.protocol.startswith("official")
    assert fg.lpips is None and fg.lpips_reason  # no weights here: null with the reason
    assert 0 < fg.flip < 1 and 0 < official.flip < 1
    # the official crop is mostly shared white background: a barely trained model looks good there only
    assert official.psnr - fg.psnr > 8.0, (official.psnr, fg.psnr)  # measured: 36.7 vs 17.4 dB
    assert fg.masked_psnr < official.psnr - 4.0
    assert ev.metric_protocols["foreground.psnr"].startswith("foreground") and ev.headline == "foreground.psnr"
    assert ev.is_test_split and ev.protocol == "all"
    assert ev.images < MIN_IMAGES_WARNING and "noisy" in ev.warnings[0]
    data = ev.to_json()  # the keys of `deliffas eval --json`: official metrics at the top level, foreground nested
    assert data["metric_protocol"] == official.protocol and data["psnr"] == official.psnr and "official" not in data
    assert {"psnr", "ssim", "masked_psnr", "flip", "lpips", "lpips_reason", "protocol"} <= set(data["foreground"])
    assert "frames_protocol" not in data and json.loads(json.dumps(data)) == data
    img = cv2.imread(str(grid))
    assert img is not None and img.shape[1] >= 3 * MIN_PANEL_PX and img.shape[0] >= MIN_PANEL_PX


def test_validation_split_is_held_out_training_cameras(run30, tiny_shards):
    record = json.loads((run30 / "train_config.json").read_text())
    data = record["data"]
    assert data["validation_cameras"] and not set(data["validation_cameras"]) & set(data["train_cameras"])
    assert data["protocol"] == "all" and "auto -> all" in data["protocol_message"]
    ev = evaluate(EvalConfig(run=str(run30), split="validation"))
    assert list(ev.cameras) == data["validation_cameras"] and not ev.is_test_split
    assert 3 not in ev.cameras  # the capture's test camera


def test_protocol_resolution_and_validation_cameras(tiny_shards):
    assert resolve_protocol(str(tiny_shards), "auto")[0] == "all"
    protocol, message = resolve_protocol(str(tiny_shards), "paper")
    assert protocol == "paper" and "1 of 6" in message
    assert validation_cameras([0, 1, 2], 1) == [1] and validation_cameras([0, 1, 2, 4], 2) == [1, 4]
    assert validation_cameras([0, 1, 2], (2,)) == [2] and validation_cameras([0, 1], 0) == []
    with pytest.raises(ValueError, match="no training camera"):
        validation_cameras([0, 1], 2)
    with pytest.raises(ValueError, match="not training cameras"):
        validation_cameras([0, 1], (3,))


def test_cli_eval_json_and_bad_values(run30, capsys):
    assert cli_main(["eval", str(run30), "--split", "validation", "--protocol", "all", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["split"] == "validation" and out["foreground"]["psnr"] is not None
    for bad in (["--protocol", "some"], ["--split", "test"]):
        with pytest.raises(SystemExit) as exc:
            cli_main(["eval", str(run30), *bad])
        assert exc.value.code == 2
        assert "error:" in capsys.readouterr().err
