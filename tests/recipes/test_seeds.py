"""recipes.seeds (mean ± std over seeds, orderings with a margin) and the single-surface ablation in quick mode."""

from __future__ import annotations

import json

import pytest

from recipes.seeds import aggregate, ordering, stats_table


def _row(name: str, fg_psnr: list[float], flip: list[float]) -> dict:
    per_seed = [{"seed": i, "fg_psnr": p, "fg_flip": f, "fg_ssim": 0.9, "masked_psnr": p - 3, "pose_fg_psnr": p - 1,
                 "train_fg_psnr": p + 1, "psnr": p + 10} for i, (p, f) in enumerate(zip(fg_psnr, flip))]
    return {"name": name, "seeds": list(range(len(fg_psnr))), "stats": aggregate(per_seed)}


def test_aggregate_and_orderings():
    single = _row("single", [20.0, 21.0, 22.0], [0.30, 0.31, 0.29])
    two = _row("two", [22.0, 23.5, 23.0], [0.25, 0.26, 0.27])
    assert single["stats"]["fg_psnr"]["mean"] == pytest.approx(21.0)
    assert single["stats"]["fg_psnr"]["std"] == pytest.approx(1.0)
    o = ordering("two >= single + 1.5", two, single, "fg_psnr", 1.5)
    assert o.difference == pytest.approx(11 / 6) and o.holds and o.seeds_holding == "2 of 3"  # paired: 2, 2.5, 1
    assert o.noise == pytest.approx(((1.0 + 7 / 12) / 3) ** 0.5) and o.within_noise  # sample variances 1, 7/12
    assert not ordering("two >= single + 3", two, single, "fg_psnr", 3.0).holds
    lower = ordering("two <= single (FLIP)", two, single, "fg_flip", 0.0, higher_is_better=False)
    assert lower.holds and lower.seeds_holding == "3 of 3" and "HOLDS" in lower.sentence("")
    one = _row("one", [20.0], [0.3])
    assert one["stats"]["fg_psnr"]["std"] == 0.0 and ordering("x", one, one, "fg_psnr", 0.0).noise is None
    table = stats_table([single, two])
    assert table[2].startswith("| single | 3 | 21.00 ± 1.00 |") and len(table) == 4


@pytest.mark.slow
def test_ablation_single_surface_quick(tiny_recipe_capture, tmp_path):
    from recipes import ablation_single_surface

    out = tmp_path / "single"
    payload = ablation_single_surface.main(["--quick", "--shards", str(tiny_recipe_capture.shards), "--out", str(out),
                                            "--viewdir-pe-freqs", "2"])
    data = json.loads((out / "results.json").read_text())
    assert data["seeds"] == [0] and data["model_overrides"] == {"viewdir_pe_freqs": 2}
    assert [r["name"] for r in data["results"]] == [label for label, _ in ablation_single_surface.ROWS]
    claim = data["claims"]["two_surface_margin"]
    assert claim["target"] == ablation_single_surface.TARGET_DB and claim["holds"] in (True, False)
    md = (out / "results.md").read_text()
    assert "Mean ± std over training seeds" in md and "two-surface >= single-surface + 1.5 dB (fg PSNR)" in md
    assert payload["title"] == data["title"]
    assert data["rows"] == ["a", "b", "c", "d"] and data["settings"]["viewdir_pe_freqs"] == 2
    assert "Investigation settings: 4 capture cameras (3 training, 1 held out)" in md
    with pytest.raises(SystemExit):
        ablation_single_surface.main(["--quick", "--out", str(tmp_path / "x"), "--seeds", "0"])
    for bad in (["--rows", "a,e"], ["--rows", ","], ["--unet-dropout", "1.0"], ["--viewdir-pe-freqs", "-1"]):
        with pytest.raises(SystemExit):
            ablation_single_surface.main(["--quick", "--out", str(tmp_path / "x"), *bad])


@pytest.mark.slow
def test_viewdir_investigation_options(tmp_path):
    """--rows a,b --cameras N --viewdir-pe-freqs 0 --unet-dropout 0.1: only the two rows train, on a capture with
    N cameras, with the raw direction and dropout 0.1, and the report says so."""
    import torch

    from deliffas.models.checkpoint import load_checkpoint
    from recipes import ablation_single_surface

    out = tmp_path / "viewdir"
    ablation_single_surface.main(["--quick", "--out", str(out), "--rows", "a,b", "--cameras", "8",
                                  "--viewdir-pe-freqs", "0", "--unet-dropout", "0.1"])
    data = json.loads((out / "results.json").read_text())
    assert [r["name"] for r in data["results"]] == [label for label, _ in ablation_single_surface.ROWS[:2]]
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["single_surface", "single_surface_viewdir"]
    assert data["settings"] == {"cameras": 8, "train_cameras": 6, "test_cameras": 2, "viewdir_pe_freqs": 0,
                                "viewdir_pe_freqs_is_preset_default": False,
                                "viewdir_encoding": "raw direction only (3 inputs, no sin/cos)", "unet_dropout": 0.1}
    assert set(data["claims"]) == {"viewdir_vs_single"}  # the two-surface claims need row d
    md = (out / "results.md").read_text()
    assert "8 capture cameras (6 training, 2 held out)" in md and "U-Net dropout 0.1" in md
    assert "8 cameras, view-direction PE 0, U-Net dropout 0.1" in data["title"]
    model = load_checkpoint(out / "runs" / "single_surface_viewdir" / "seed0" / "checkpoint").model
    assert model.config.viewdir_pe_freqs == 0 and model.config.unet.dropout == 0.1
    assert [m.p for m in model.modules() if isinstance(m, torch.nn.Dropout)] == [0.1] * 3


def test_coarse_mesh_variants_checked(tmp_path):
    from recipes import ablation_coarse_mesh

    for bad in ("original", "smooth,coarse", "original,smooth,fine"):
        with pytest.raises(SystemExit):
            ablation_coarse_mesh.main(["--quick", "--out", str(tmp_path), "--variants", bad])
