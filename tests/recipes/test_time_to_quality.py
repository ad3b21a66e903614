"""The time-to-quality and where-it-fails recipes in quick mode: output structure, curves, charts."""

from __future__ import annotations

import json
import math

import pytest

from deliffas.engine.time_budget import CALIBRATION

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_time_to_quality_quick(tiny_recipe_capture, tmp_path):
    from recipes import time_to_quality

    out = tmp_path / "ttq"
    payload = time_to_quality.main(["--quick", "--out", str(out), "--shards", str(tiny_recipe_capture.shards)])
    data = json.loads((out / "results.json").read_text())
    assert data["title"] == payload["title"] and data["quick"] is True
    names = [c["name"] for c in data["configurations"]]
    budgets = [f"default, {b:g} s budget" for b in time_to_quality.QUICK_BUDGETS]
    assert names == [*time_to_quality.CONFIGS, *budgets]
    for config in data["configurations"]:
        (curve,) = config["curves"]
        if config["name"] in budgets:  # one point, at the length the run planned
            (point,) = curve
            assert point["iteration"] >= CALIBRATION and point["budget_s"] == config["fields"]["time_budget"]
            assert math.isfinite(point["validation"]["masked_psnr"])
            continue
        assert [p["iteration"] for p in curve] == sorted({max(1, round(f * config["iters"]))
                                                          for f in time_to_quality.CHECKPOINTS})
        assert all(b["train_s"] >= a["train_s"] for a, b in zip(curve, curve[1:]))
        for point in curve:
            assert math.isfinite(point["validation"]["masked_psnr"]) and math.isfinite(point["novel_view"]["fg_psnr"])
    assert (out / "time_to_quality.png").read_bytes()[:8] == PNG_SIGNATURE
    assert "| default |" in (out / "results.md").read_text()


@pytest.mark.slow
def test_where_it_fails_quick(tmp_path):
    from recipes import where_it_fails

    out = tmp_path / "wif"
    where_it_fails.main(["--quick", "--out", str(out), "--models", "two_surface,default", "--default-seeds", "2"])
    data = json.loads((out / "results.json").read_text())
    assert data["seeds"] == {"two_surface": [0], "default": [0, 1]}
    assert set(data["cameras"]) == {"2", "3"} and set(data["sizes"]) == {"32", "64"}
    for sweep in (data["cameras"], data["sizes"]):
        for point in sweep.values():
            assert set(point) == {"two_surface", "default"}
            assert [len(point[m]["per_seed"]) for m in ("two_surface", "default")] == [1, 2]
            assert all(math.isfinite(m["masked_psnr"]) for m in point.values())
    budget = data["error_budget"]["seed 0"]
    assert set(data["error_budget"]) == {"seed 0", "seed 1"}
    shares = [c["error_share"] for name, c in budget["classes"].items() if name != "background"]
    assert sum(shares) == pytest.approx(1.0)
    for name in ("cameras.png", "sizes.png", "error_budget.png"):
        assert (out / name).read_bytes()[:8] == PNG_SIGNATURE
