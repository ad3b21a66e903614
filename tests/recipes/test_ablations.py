"""The template-quality, perceptual and template-vs-body-model ablations in quick mode: output structure.

Each recipe runs once on the shared quick capture (``tiny_recipe_capture``); the numbers of a few
tiny-preset iterations only show the pipeline works, so only structure and finiteness are checked.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _perceptual_status() -> dict:
    from deliffas.models.metrics import perceptual_metrics_status

    return perceptual_metrics_status()


def _check_png(path: Path) -> None:
    import cv2

    assert path.is_file(), path
    assert path.read_bytes()[:8] == PNG_MAGIC, f"{path} is not a PNG"
    img = cv2.imread(str(path))
    assert img is not None and img.ndim == 3 and min(img.shape[:2]) > 100, path


def _check_outputs(out: Path, payload: dict, num_rows: int, charts: tuple[str, ...]) -> dict:
    """Structure shared by every recipe; returns results.json."""
    data = json.loads((out / "results.json").read_text())
    assert data["title"] == payload["title"]
    for key in ("title", "results", "quick", "sizes", "command", "claims"):
        assert key in data, key
    assert data["quick"] is True and "quick mode" in data["title"]
    rows = data["results"]
    assert len(rows) == num_rows
    assert len({r["name"] for r in rows}) == num_rows, "one row per configuration"
    status = _perceptual_status()
    for r in rows:
        assert math.isfinite(r["psnr"]) and 0 < r["psnr"] < 100, r["name"]
        assert math.isfinite(r["ssim"]) and 0 < r["ssim"] <= 1, r["name"]
        assert r["fid"] is None and r["fid_reason"]
        if status["lpips"] is None:  # offline: no LPIPS weights
            assert r["lpips"] is None and "LPIPS" in r["lpips_reason"]
        assert math.isfinite(r["lpips_random_vgg16"]) and r["lpips_random_vgg16"] >= 0
        assert r["lpips_random_vgg16_backbone"]["name"] == "vgg16-random"
        assert set(r["stage_ms"]) == {"uv", "cnn", "sample", "mlp"}
        if "stats" in r:  # the seeded ablations: mean ± std in foreground metrics, grids per run
            assert r["seeds"] == [s["seed"] for s in r["per_seed"]]
            assert r["stats"]["fg_psnr"]["mean"] == pytest.approx(r["foreground"]["psnr"])  # one seed in quick mode
            assert r["stats"]["fg_psnr"]["mean"] < r["psnr"]
            assert r["novel_pose"]["foreground"]["psnr"] is not None and r["train_fit"]["foreground"]["psnr"] is not None
            for split in ("novel_view", "novel_pose"):
                _check_png(Path(r["run"]) / f"grid_{split}.png")
    md = (out / "results.md").read_text()
    assert md.startswith(f"# {data['title']}\n")
    assert md.count("\n| ") >= num_rows + 1  # header + one line per row (+ extra tables)
    if status["lpips"] is None:
        assert "LPIPS unavailable" in md
    for name in ("speed_accuracy.png", *charts):
        _check_png(out / name)
        assert name in md
    return data


@pytest.mark.slow
def test_ablation_coarse_mesh_quick(tiny_recipe_capture, tmp_path):
    """From existing shards: the subject recorded in their manifest is re-converted per template variant."""
    from recipes import ablation_coarse_mesh

    out = tmp_path / "coarse"
    payload = ablation_coarse_mesh.main(["--quick", "--shards", str(tiny_recipe_capture.shards), "--out", str(out)])
    data = _check_outputs(out, payload, 6, ("psnr_by_template.png",))
    assert {(r["template"], r["variant"]) for r in data["results"]} == {
        (t, m) for t in ("original", "smooth", "coarse") for m in ("single_surface", "two_surface")}
    assert data["subject"] == str(tiny_recipe_capture.subject)
    assert data["convert_sizes"]["atlas_res"] == tiny_recipe_capture.sizes.atlas_res
    geo = data["templates"]
    assert geo["original"]["deviation_mean_mm"] == pytest.approx(0.0, abs=1e-6)
    assert geo["coarse"]["faces"] <= ablation_coarse_mesh.COARSE_FACES < geo["original"]["faces"]
    assert geo["smooth"]["faces"] == geo["original"]["faces"] and geo["smooth"]["deviation_mean_mm"] > 1.0
    for g in geo.values():
        assert 0.0 <= g["inner_outside_mask"] < 1.0 and 0.0 <= g["mask_missed"] < 1.0
    assert geo["original"]["inner_outside_mask"] == 0.0  # the synthetic person is the template plus an outward garment
    for model in ("single_surface", "two_surface"):
        for variant in ("smooth", "coarse"):
            assert math.isfinite(data["losses_vs_original"][model][variant]["psnr_loss_db"])
    claims = data["claims"]
    assert claims["two_surface_loses_less_on_coarse"] in (True, False, None)  # None: neither model loses
    assert claims["two_surface_loses_less_on_smooth"] in (True, False, None)
    md = (out / "results.md").read_text()
    assert "two-surface loses less" in md and "Quick mode" in md
    for variant in ("original", "smooth", "coarse"):
        assert (out / "templates" / variant / "outer.obj").is_file()
        assert json.loads((out / f"shards_{variant}" / "manifest.json").read_text())["config"]["template"].endswith(variant)


@pytest.mark.slow
def test_ablation_perceptual_quick(tiny_recipe_capture, tmp_path, capsys):
    from recipes import ablation_perceptual

    out = tmp_path / "perceptual"
    payload = ablation_perceptual.main(["--quick", "--shards", str(tiny_recipe_capture.shards), "--out", str(out)])
    data = _check_outputs(out, payload, 3, ("perceptual_metric.png", "psnr.png"))
    rows = data["results"]
    assert [r["perceptual"] == "none" for r in rows] == [True, False, False]
    assert [r["perceptual_mode"] for r in rows] == [None, "patch", "image"]
    backbone = data["perceptual_backbone"]
    if ablation_perceptual.imagenet_weights_found() is None:
        assert backbone == "vgg16-random"
        assert "vgg16-random" in data["title"] and "not ImageNet" in data["title"]
        assert "ABSENT" in capsys.readouterr().out
    for r in rows[1:]:
        assert r["perceptual_backbone"]["name"] == backbone
        if backbone == "vgg16-random":
            assert r["perceptual_backbone"]["seed"] == 1  # the recipe's default: not the metric's seed 0
            assert r["lpips_random_vgg16_backbone"]["seed"] == 0
        assert r["stage2_from_iteration"] == int(0.5 * tiny_recipe_capture.sizes.iters)
        log = [json.loads(x) for x in (Path(r["run"]) / "log.jsonl").read_text().splitlines()]
        assert log[-1]["stage"] == 2 and log[-1]["perceptual_weight"] > 0
        st = r["stage2_per_seed"][0]  # the weighted perceptual term is balanced with the step's L1
        assert st["weight"] == log[-1]["perceptual_weight"] and 0.25 < st["share_of_l1_first"] < 4.0, st
    assert rows[0]["stage2_per_seed"] == [None]  # L1 only
    claims = data["claims"]
    assert claims["perceptual_metric"] == "fg_flip"  # judged on FLIP in the foreground box (issue 18)
    assert claims["lpips_family_metric"] == (
        "lpips" if all(r["lpips"] is not None for r in rows) else "lpips_random_vgg16")
    assert isinstance(claims["image_beats_patch_on_perceptual_metric"], bool)
    assert claims["image_le_patch_on_flip"]["seeds_holding"] == "0 of 1" or \
        claims["image_le_patch_on_flip"]["seeds_holding"] == "1 of 1"
    md = (out / "results.md").read_text()
    assert "Perceptual metric used for the comparison" in md and "substitute" in md.lower()
    assert "Stage 2 as trained" in md and "b. weight" in md and "c. weight" in md


def test_ablation_perceptual_rejects_bad_start(tmp_path):
    from recipes import ablation_perceptual

    with pytest.raises(SystemExit):
        ablation_perceptual.main(["--quick", "--out", str(tmp_path), "--perceptual-start", "1.5"])


@pytest.mark.slow
def test_ablation_template_quick_standin(tiny_recipe_capture, tmp_path, capsys):
    """Without --smpl-model: the DDC-style template against the decimated + smoothed stand-in, said so."""
    from recipes import ablation_template

    out = tmp_path / "template"
    payload = ablation_template.main(["--quick", "--subject", str(tiny_recipe_capture.subject), "--out", str(out)])
    data = _check_outputs(out, payload, 4, ("psnr_by_template.png",))
    assert data["body_model"] == "standin" and data["claims"]["comparison"] == "standin"
    assert "stand-in" in data["title"] and "no SMPL" in data["title"]
    assert "no --smpl-model given" in data["comparison"]
    assert "comparison: " in capsys.readouterr().out
    assert {(r["template"], r["variant"]) for r in data["results"]} == {
        (t, m) for t in ("original", "standin") for m in ("single_surface", "two_surface")}
    g = data["templates"]["standin"]
    assert g["faces"] <= ablation_template.STANDIN_FACES and g["deviation_mean_mm"] > 1.0
    assert 0.0 <= g["mask_missed"] < 1.0 and 0.0 <= g["inner_outside_mask"] < 1.0
    assert "Comparison run:" in (out / "results.md").read_text()
    assert data["claims"]["two_surface_loses_less"] in (True, False, None)
    assert data["seeds"] == [0] and all("stats" in r for r in data["results"])  # --seeds: 1 in quick mode
    by = {(r["variant"], r["template"]): r for r in data["results"]}
    for model in ("single_surface", "two_surface"):  # the loss is paired by seed, in foreground PSNR
        expected = by[(model, "original")]["stats"]["fg_psnr"]["mean"] - by[(model, "standin")]["stats"]["fg_psnr"]["mean"]
        assert data["fg_psnr_loss_vs_original_db"][model] == pytest.approx(expected)
        assert data["fg_psnr_loss_std_db"][model] == 0.0
    assert "Mean ± std over training seeds" in (out / "results.md").read_text()


def test_loses_less_needs_a_loss():
    from recipes.ablation_coarse_mesh import loses_less, verdict

    assert loses_less(1.7, 1.2) is True and loses_less(0.2, 0.5) is False
    assert loses_less(-0.1, -0.3) is None and verdict(None) == "neither loses"
    assert loses_less(0.0, 0.4) is False  # the two-surface model lost, the single-surface one did not


def test_ablation_template_missing_smpl_file(tmp_path, capsys):
    from recipes import ablation_template

    with pytest.raises(SystemExit):
        ablation_template.main(["--quick", "--out", str(tmp_path), "--smpl-model", str(tmp_path / "none.npz")])
    assert "not shipped" in capsys.readouterr().err


@pytest.mark.slow
def test_ablation_template_quick_smpl_through_shards(tiny_recipe_capture, tmp_path):
    """--smpl-model procedural: SMPL fitted to every frame, the same images converted with the smpl template
    and the fitted per-frame parameters, single and two surfaces trained on both templates."""
    from deliffas.data.shards import ShardSet
    from recipes import ablation_template

    out = tmp_path / "template_smpl"
    payload = ablation_template.main(["--quick", "--subject", str(tiny_recipe_capture.subject), "--out", str(out),
                                      "--smpl-model", "procedural", "--smpl-fit-iters", "30"])
    data = _check_outputs(out, payload, 4, ("psnr_by_template.png",))
    assert data["body_model"] == "smpl" and "fitted to every frame" in data["comparison"]
    assert {(r["template"], r["variant"]) for r in data["results"]} == {
        (t, m) for t in ("original", "smpl") for m in ("single_surface", "two_surface")}
    assert ShardSet(out / "shards_smpl").meta.template_spec().kind == "smpl"
    g = data["templates"]["smpl"]
    assert np.isfinite(g["deviation_mean_mm"]) and 0.0 <= g["mask_missed"] < 1.0
