"""recipes.presets in quick mode: two presets over two seeds, the real-time claim tested paired by seed."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_presets_quick(tiny_recipe_capture, tmp_path):
    from recipes import presets

    out = tmp_path / "presets"
    presets.main(["--quick", "--shards", str(tiny_recipe_capture.shards), "--out", str(out), "--seeds", "2",
                  "--saturation-weight", "0"])
    data = json.loads((out / "results.json").read_text())
    assert data["presets"] == ["realtime", "small"] and data["seeds"] == [0, 1] and data["saturation_weight"] == 0
    assert [r["name"] for r in data["results"]] == ["realtime", "small"]
    assert all(len(r["per_seed"]) == 2 for r in data["results"])
    claim = data["claims"]["realtime_within_0.5_db_of_small"]
    assert claim["target"] == presets.REALTIME_MARGIN_DB and claim["seeds_holding"].endswith("of 2")
    md = (out / "results.md").read_text()
    assert "realtime >= small -0.5 dB (fg PSNR)" in md and "saturation weight 0" in md


def test_preset_list_is_checked():
    from recipes.presets import parse_presets

    assert parse_presets(None) == ["realtime", "small"]
    assert parse_presets("paper, realtime") == ["paper", "realtime"]
    for bad in ("huge", "small,small", ","):
        with pytest.raises(ValueError, match="--presets"):
            parse_presets(bad)
