"""auto_capacity: every candidate trained and recorded, the choice obeys the rule, the CLI flag works."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from deliffas.engine.auto_capacity import AutoCapacityConfig, Candidate, auto_capacity, choose, default_ladder
from deliffas.engine.train import TrainConfig


def _rule_holds(record: dict) -> None:
    """Recompute the rule from the recorded numbers alone (not through ``choose``)."""
    cost = record["cost"]
    q = record["selection_metric"].split()[0]  # the quality the rule ranks by (foreground PSNR)
    assert q == "fg_psnr"
    ok = [c for c in record["candidates"] if c["error"] is None and math.isfinite(c[q])]
    best = max(c[q] for c in ok)
    assert record["best_psnr"] == pytest.approx(best)
    chosen = next(c for c in record["candidates"] if c["name"] == record["choice"])
    assert chosen["error"] is None
    assert chosen[q] >= best - record["tolerance_db"]
    eligible = [c for c in ok if c[q] >= best - record["tolerance_db"]]
    cheapest = min(c[cost] for c in eligible)
    assert chosen[cost] <= cheapest * (1 + record["ms_tie_rel"]) + 1e-9
    tied = [c for c in eligible if c[cost] <= cheapest * (1 + record["ms_tie_rel"])]
    assert chosen["num_parameters"] == min(c["num_parameters"] for c in tied)


def test_choose_rule_on_records():
    recs = [
        {"name": "big", "psnr": 30.0, "frame_ms": 50.0, "num_parameters": 1000, "error": None},
        {"name": "mid", "psnr": 29.7, "frame_ms": 20.0, "num_parameters": 500, "error": None},
        {"name": "mid_tied", "psnr": 29.6, "frame_ms": 20.5, "num_parameters": 300, "error": None},
        {"name": "small", "psnr": 28.0, "frame_ms": 10.0, "num_parameters": 100, "error": None},
        {"name": "broken", "psnr": None, "frame_ms": None, "num_parameters": None, "error": "ValueError: x"},
    ]
    assert choose(recs, 0.5, ms_tie_rel=0.05) == ("mid_tied", 30.0)  # 20.5 ms ties with 20 ms: fewer parameters
    assert choose(recs, 0.5, ms_tie_rel=0.0) == ("mid", 30.0)
    assert choose(recs, 0.1, ms_tie_rel=0.0) == ("big", 30.0)
    assert choose(recs, 5.0, ms_tie_rel=0.0) == ("small", 30.0)
    assert choose(recs[-1:], 0.5) == (None, None)


def test_default_ladder_small_to_large():
    ladder = default_ladder("two_surface", "tiny")
    assert len(ladder) >= 3 and len({c.name for c in ladder}) == len(ladder)
    from deliffas.models.deliffas import DeliffasModel
    from deliffas.models.checkpoint import config_from_dict, config_to_dict
    from deliffas.models.zoo import get_config

    params = []
    for c in ladder:
        base = config_to_dict(get_config("two_surface", "tiny"))
        for key, value in c.overrides.items():
            base[key] = {**base[key], **value}
        params.append(DeliffasModel(config_from_dict(type(get_config("two_surface", "tiny")), base)).num_parameters())
    assert params == sorted(params)
    # the preset itself is a rung
    assert any(c.overrides["mlp"]["width"] == 32 and c.overrides["unet"]["base_channels"] == 4 for c in ladder)


def test_auto_capacity_records_all_and_chooses_by_rule(tiny_shards, tmp_path):
    cfg = TrainConfig(shards=str(tiny_shards), out=str(tmp_path / "search"), model="single_surface", preset="tiny",
                      iters=3, cameras_per_frame=2, protocol="all", num_workers=1, progress=False,
                      checkpoint_every=100, preview_every=0)
    candidates = [Candidate("narrow", {"mlp": {"width": 8}, "unet": {"base_channels": 2, "max_channels": 4}}),
                  Candidate("preset", {}),
                  {"mlp": {"width": 64, "depth": 3, "feature_layer": 1}}]
    ac = AutoCapacityConfig(tolerance_db=0.5, candidates=candidates, max_frames=1)
    result = auto_capacity(cfg, ac)
    record = json.loads((tmp_path / "search" / "auto_capacity.json").read_text())
    assert record == json.loads(json.dumps(result, default=str))
    names = [c["name"] for c in record["candidates"]]
    assert names[:2] == ["narrow", "preset"] and len(names) == 3
    for c in record["candidates"]:
        assert c["error"] is None, c.get("traceback")
        assert math.isfinite(c["psnr"]) and c["frame_ms"] > 0 and c["num_parameters"] > 0
        assert set(c["stage_ms"]) == {"uv", "cnn", "sample", "mlp"}
        assert Path(c["run"], "checkpoint", "config.json").is_file()
    assert record["candidates"][0]["num_parameters"] < record["candidates"][1]["num_parameters"] \
        < record["candidates"][2]["num_parameters"]
    _rule_holds(record)
    _selection_is_never_the_test_split(record)
    chosen = tmp_path / "search" / "chosen"
    assert (chosen / "checkpoint" / "config.json").is_file()
    assert chosen.resolve() == Path(record["chosen_run"]).resolve()


def test_config_validation(unchecked):
    with unchecked(), pytest.raises(ValueError, match="tolerance_db"):
        AutoCapacityConfig(tolerance_db=-1)
    for test_split in ("novel_view", "novel_pose"):
        with unchecked(), pytest.raises(ValueError, match="test split"):
            AutoCapacityConfig(split=test_split)
    with unchecked(), pytest.raises(ValueError, match="split"):
        AutoCapacityConfig(split="everything")
    with unchecked(), pytest.raises(ValueError, match="validation_cameras"):
        AutoCapacityConfig(validation_cameras=0)


def _selection_is_never_the_test_split(record: dict) -> None:
    from deliffas.engine.data_bridge import TEST_SPLITS

    assert record["selection_split"] == "validation" and record["selection_split"] not in TEST_SPLITS
    val = record["validation_cameras"]
    assert val and not set(val) & set(record["test_cameras"])
    for c in record["candidates"]:
        run_record = json.loads(Path(c["run"], "train_config.json").read_text())
        assert run_record["data"]["validation_cameras"] == val  # every candidate held out the same cameras
        assert not set(val) & set(run_record["data"]["train_cameras"])  # and never trained on them
    if record["test_cameras"]:
        assert record["test"]["split"] == "novel_view" and record["test"]["candidate"] == record["choice"]


def test_cli_auto_capacity(tiny_shards, tmp_path):
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-m", "deliffas", "train", str(tiny_shards), "--auto-capacity",
                        "--tolerance-db", "1.0", "--out", str(run), "--preset", "tiny", "--iters", "2",
                        "--preview-every", "0"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    printed = json.loads(r.stdout)
    record = json.loads((run / "auto_capacity.json").read_text())
    assert printed["choice"] == record["choice"] and record["tolerance_db"] == 1.0 and record["iters"] == 2
    assert [c["name"] for c in record["candidates"]] == [c.name for c in default_ladder("two_surface", "tiny")]
    _rule_holds(record)
    _selection_is_never_the_test_split(record)
    assert (run / "chosen" / "checkpoint" / "weights.safetensors").is_file()
