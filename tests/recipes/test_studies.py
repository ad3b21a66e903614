"""The speed/accuracy and stability recipes in quick mode on the shared tiny capture: structure, numbers, charts."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _valid_png(path) -> None:
    import cv2

    path = Path(path)
    assert path.is_file(), path
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    img = cv2.imread(str(path))
    assert img is not None and img.shape[0] > 100 and img.shape[1] > 100


def _finite_or_error(row: dict, keys=("psnr", "ssim")) -> bool:
    """True for a usable row (finite numbers), False for a recorded error; anything else fails the test."""
    if row.get("error"):
        assert isinstance(row["error"], str)
        return False
    for k in keys:
        assert isinstance(row[k], float) and math.isfinite(row[k]), (row.get("name"), k, row.get(k))
    return True


def _args(capture, out) -> list[str]:
    return ["--quick", "--out", str(out), "--shards", str(capture.shards), "--subject", str(capture.subject)]


@pytest.fixture(scope="module")
def speed(tiny_recipe_capture, tmp_path_factory):
    from recipes import speed_accuracy

    out = tmp_path_factory.mktemp("speed_accuracy")
    return out, speed_accuracy.main(_args(tiny_recipe_capture, out))


@pytest.fixture(scope="module")
def stability(tiny_recipe_capture, tmp_path_factory):
    from recipes import stability

    out = tmp_path_factory.mktemp("stability")
    # a variant that does not exist: every configuration of it must become a recorded error
    variants = "single_surface,two_surface,no_such_model"
    return out, stability.main(_args(tiny_recipe_capture, out) + ["--variants", variants])


@pytest.mark.slow
def test_speed_accuracy_rows_and_pareto(speed, tiny_recipe_capture):
    from deliffas.engine.report import pareto_front
    from recipes.speed_accuracy import HEADLINE, VARIANTS, SweepPlan

    out, payload = speed
    written = json.loads((out / "results.json").read_text())
    assert written["results"] == json.loads(json.dumps(payload["results"], default=str))
    rows = payload["results"]
    plan = SweepPlan.for_mode(True)
    knobs = [r["knob"] for r in rows]
    assert [r["name"] for r in rows[:4]] == list(VARIANTS)
    assert knobs.count("mlp") == len(plan.mlp) and knobs.count("unet") == len(plan.unet)
    assert knobs.count("atlas") == len(plan.atlas) and knobs.count("template") == len(plan.coarse)
    usable = []
    assert payload["seeds"] == [0]  # --seeds: 1 in quick mode
    for r in rows:
        if _finite_or_error(r, ("psnr", "ssim", HEADLINE)):
            assert r["seeds"] == [0] and r[HEADLINE] == pytest.approx(r["foreground"]["psnr"])
            assert set(r["stage_ms"]) == {"uv", "cnn", "sample", "mlp"}
            assert r["num_parameters"] > 0 and r["fps"] > 0
            assert r["ms_per_frame"] == pytest.approx(sum(r["stage_ms"].values()))
            assert isinstance(r["pareto"], bool)
            usable.append(r)
        else:
            assert r["pareto"] is None
    assert len(usable) >= 4  # at least the four variants train on the tiny capture
    front = pareto_front([r["ms_per_frame"] for r in usable], [r[HEADLINE] for r in usable])  # foreground PSNR
    assert {usable[i]["name"] for i in front} == {r["name"] for r in usable if r["pareto"]}
    assert payload["pareto_front"] == [usable[i]["name"] for i in front]
    side = tiny_recipe_capture.sizes.size
    assert payload["resolution"] == [side, side]
    md = (out / "results.md").read_text()
    assert "on Pareto front" in md and f"{side}x{side}" in md and "Mean ± std over training seeds" in md
    for r in rows:
        assert r["name"] in md
    _valid_png(out / "speed_accuracy.png")
    for path in payload["charts"].values():
        _valid_png(path)


def test_mark_pareto_skips_errors():
    from recipes.speed_accuracy import HEADLINE, mark_pareto

    rows = [{"name": "a", HEADLINE: 20.0, "stage_ms": {"uv": 1.0, "mlp": 1.0}},
            {"name": "b", HEADLINE: 25.0, "stage_ms": {"uv": 3.0, "mlp": 1.0}},
            {"name": "c", HEADLINE: 22.0, "stage_ms": {"uv": 5.0, "mlp": 1.0}},
            {"name": "d", HEADLINE: None, "stage_ms": None, "error": "RuntimeError: boom"},
            {"name": "e", HEADLINE: float("nan"), "stage_ms": {"uv": 0.5, "mlp": 0.1}}]
    mark_pareto(rows)
    assert [r["pareto"] for r in rows] == [True, True, False, None, None]


@pytest.mark.slow
def test_stability_structure_and_fail_rule(stability):
    from recipes.stability import HEADLINE, SWEEPS, StabilityPlan

    out, payload = stability
    assert payload["seeds"] == [0] and payload["metric"] == HEADLINE == "fg_psnr_mean"
    assert json.loads((out / "results.json").read_text())["failures"] == payload["failures"]
    rows = payload["results"]
    plan = StabilityPlan.for_mode(True)
    variants = ["single_surface", "two_surface", "no_such_model"]
    assert payload["variants"] == variants
    n_train = 3  # quick capture: 4 cameras, 1 held out
    expected = {"offset": 2 * len(plan.offsets_mm), "smoothing": len(plan.smooth_iters),
                "cameras": len([c for c in plan.train_cameras if c < n_train]) + 1,
                "pose_distance": 1 + plan.pose_bins, "holes": len(plan.holes)}
    for sweep in SWEEPS:
        for v in variants:
            group = [r for r in rows if r["sweep"] == sweep and r["variant"] == v]
            if v == "no_such_model":
                assert group and all(r["error"] and r["failed"] for r in group), sweep
                continue
            assert len(group) == expected[sweep], (sweep, v, [r["label"] for r in group])
            usable = [r for r in group if _finite_or_error(r, ("psnr", "ssim", HEADLINE))]
            assert usable, (sweep, v)
            assert all(r["seeds"] == [0] and r[HEADLINE] == r["stats"]["fg_psnr"]["mean"] for r in usable)
            best = max(r[HEADLINE] for r in usable)
            for r in group:
                assert r["best_psnr"] == pytest.approx(best)
                should_fail = bool(r["error"]) or best - r[HEADLINE] > payload["fail_db"]
                assert r["failed"] == should_fail, r["name"]
            listed = payload["failures"][sweep][v]
            assert len(listed) == sum(r["failed"] for r in group)
        _valid_png(out / f"stability_{sweep}.png")
        assert Path(payload["charts"][sweep]).name == f"stability_{sweep}.png"
    offset = [r for r in rows if r["sweep"] == "offset" and r["variant"] == "two_surface"]
    assert {r["series"] for r in offset} == {"plain", "safe"}
    assert {r["value"] for r in offset} == set(plan.offsets_mm)
    cams = [r for r in rows if r["sweep"] == "cameras" and r["variant"] == "two_surface"]
    assert sorted(len(r["train_cameras"]) for r in cams) == sorted(r["value"] for r in cams)
    pose = [r for r in rows if r["sweep"] == "pose_distance" and r["variant"] == "two_surface"]
    assert pose[0]["value"] == 0.0 and all(r["value"] > 0 for r in pose[1:])
    holes = [r for r in rows if r["sweep"] == "holes" and r["variant"] == "two_surface"]
    for r in holes:
        assert 0.0 <= r["no_exit_fraction"] <= 1.0 and 0.0 <= r["unshaded_fraction"] <= r["no_exit_fraction"]
    holed = [r for r in holes if r["value"] > 0]
    assert holed and all(r["faces_deleted"] > 0 and r["boundary_edges"] > 0 for r in holed)
    assert max(r["no_exit_fraction"] for r in holed) > holes[0]["no_exit_fraction"]
    md = (out / "results.md").read_text()
    for sweep in SWEEPS:
        assert f"## {sweep}" in md and f"stability_{sweep}.png" in md


def test_stability_two_seeds(tiny_recipe_capture, tmp_path):
    """--seeds 2: each configuration trained twice (runs/KEY/VARIANT/seed<S>), rows are mean ± std over both,
    also the pose-distance rows scored from every seed's run."""
    from recipes import stability

    out = tmp_path / "stability2"
    payload = stability.main(_args(tiny_recipe_capture, out) + ["--sweeps", "pose_distance", "--variants",
                                                                "two_surface", "--seeds", "2"])
    assert payload["seeds"] == [0, 1]
    rows = payload["results"]
    assert len(rows) == 1 + stability.StabilityPlan.for_mode(True).pose_bins
    for r in rows:
        assert r["error"] is None and r["seeds"] == [0, 1] and [s["seed"] for s in r["per_seed"]] == [0, 1]
        values = r["stats"]["fg_psnr"]["values"]
        assert len(values) == 2 and all(math.isfinite(v) for v in values)
        assert r["fg_psnr_mean"] == pytest.approx(sum(values) / 2) and r["stats"]["fg_psnr"]["std"] > 0
    for seed in (0, 1):
        assert (out / "runs" / "base" / "two_surface" / f"seed{seed}" / "checkpoint").is_dir()
    assert " ± " in (out / "results.md").read_text()
