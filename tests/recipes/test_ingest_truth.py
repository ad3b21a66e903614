"""The ingest-against-the-truth recipe in quick mode, and its pure parts against known answers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.data.test_ingest_real import needs_detector


def test_mask_iou_known_answers():
    from recipes.ingest_truth import mask_iou

    a = np.zeros((4, 4), np.uint8)
    b = np.zeros((4, 4), np.uint8)
    assert mask_iou(a, b) == 1.0
    a[:2] = 255
    b[1:3] = 255
    assert mask_iou(a, b) == pytest.approx(4 / 12)
    assert mask_iou(a, a) == 1.0


@pytest.mark.slow
@needs_detector
def test_quick_run_structure(tmp_path):
    from recipes.ingest_truth import CONFIGS, main

    payload = main(["--out", str(tmp_path), "--quick"])
    assert [r["name"] for r in payload["results"]] == list(CONFIGS)
    masks = payload["masks"]
    assert len(masks["per_camera"]) == 4 and 0.5 < masks["median"] <= 1.0  # the detector finds the body
    assert 0 < payload["surface"]["surface_mm_median"] < 300
    assert 0 < payload["keypoints"]["median_mm"] < 300
    assert set(payload["psnr_cost"]) == {"masks_db", "body_fit_db", "total_db"}
    for row in payload["results"]:
        assert np.isfinite(row["stats"]["masked_psnr"]["mean"]) and "own_masks" in row
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["ingest_report"]["frames"]["fitted"] >= 10
    assert "What each ingest stage costs" in (tmp_path / "results.md").read_text()
