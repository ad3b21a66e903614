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
    with pytest.raises(SystemExit):
        ablation_single_surface.main(["--quick", "--out", str(tmp_path / "x"), "--seeds", "0"])


def test_coarse_mesh_variants_checked(tmp_path):
    from recipes import ablation_coarse_mesh

    for bad in ("original", "smooth,coarse", "original,smooth,fine"):
        with pytest.raises(SystemExit):
            ablation_coarse_mesh.main(["--quick", "--out", str(tmp_path), "--variants", bad])
