"""The demo end to end at its quick size: capture, shards, two trained models, report, web page."""

from __future__ import annotations

import json
import logging
import math

from deliffas.engine import demo
from deliffas.engine.demo import DemoConfig, run_demo
from deliffas.engine.run_sizes import RunSizes


def test_quick_demo_writes_a_complete_report(tmp_path):
    report = run_demo(DemoConfig(out=str(tmp_path / "demo"), quick=True))
    out = report.parent
    payload = json.loads((out / "results.json").read_text())
    assert payload["config"]["sizes"] == RunSizes.quick().__dict__
    names = [r["name"] for r in payload["results"]]
    assert names == ["two_surface_reflect_texture", "single_surface"]
    for row in payload["results"]:
        assert math.isfinite(row["psnr"]) and row["psnr"] > 20, row  # 8 iterations already beat a blank image
        assert set(row["stage_ms"]) == {"uv", "cnn", "sample", "mlp"}
        assert (row["lpips"] is None) == bool(row.get("lpips_reason"))  # without ImageNet weights: a reason, no number
    text = report.read_text()
    assert all(n in text for n in names)
    for name in ("speed_accuracy.png", "comparison.png"):
        assert (out / name).stat().st_size > 1000
    assert "foreground PSNR" in text
    for row in payload["results"]:
        fg = row["foreground"]
        assert fg["psnr"] < row["psnr"] and row["novel_pose"]["foreground"]["psnr"] is not None
        for split in ("novel_view", "novel_pose"):
            assert (out / f"grid_{row['name']}_{split}.png").stat().st_size > 1000
    web = out / "web"  # the first model's web page beside the report
    assert (web / "index.html").is_file() and (web / "avatar.bin").stat().st_size > 1000
    assert json.loads((web / "avatar.json").read_text())["model"]["variant"] == "two_surface_reflect"
    assert "web/" in text and "python -m http.server" in text


def test_a_model_the_web_player_does_not_render_is_skipped_with_a_note(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger=demo.__name__):
        assert demo._web_page(tmp_path / "run", tmp_path / "web", "single_surface_two_unet", "tiny") is None
    assert "web page skipped" in caplog.text and "single_surface_two_unet" in caplog.text
    assert not (tmp_path / "web").exists()
