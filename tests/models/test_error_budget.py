"""models.error_budget: pixel classes and frequency bands of a prediction's error."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.models.error_budget import PIXEL_CLASSES, ErrorBudget, frequency_bands, pixel_classes


def test_bands_sum_to_the_image():
    img = np.random.default_rng(0).random((32, 40, 3)).astype(np.float32)
    bands = frequency_bands(img)
    np.testing.assert_allclose(sum(bands), img, atol=1e-5)
    assert len(bands) == 4


def test_fine_noise_lands_in_the_finest_band_and_a_flat_offset_in_the_coarsest():
    rng = np.random.default_rng(1)
    noise = rng.normal(0, 0.1, (64, 64, 3)).astype(np.float32)
    fine = [float(np.square(b).mean()) for b in frequency_bands(noise)]
    assert np.argmax(fine) == 0
    flat = [float(np.square(b).mean()) for b in frequency_bands(np.full((64, 64, 3), 0.2, np.float32))]
    assert np.argmax(flat) == 3 and flat[0] < 1e-10


def test_pixel_classes():
    mask = np.zeros((20, 20), np.float32)
    mask[4:16, 4:16] = 1
    pixels = np.array([10 * 20 + 10, 10 * 20 + 11, 4 * 20 + 4])
    cls = pixel_classes(mask, pixels, np.array([False, True, False]), boundary_px=2)
    names = np.array(PIXEL_CLASSES)
    assert names[cls[10, 10]] == "inner" and names[cls[10, 11]] == "peeled"
    assert names[cls[4, 4]] == "boundary" and names[cls[0, 0]] == "background" and names[cls[9, 9]] == "no_ray"


def test_budget_shares_add_up_and_name_where_the_error_is():
    mask = np.zeros((32, 32), np.float32)
    mask[4:28, 4:28] = 1
    gt = np.zeros((32, 32, 3), np.float32)
    gt[mask > 0] = 0.5
    pred = gt.copy()
    pred[12:20, 12:20] += 0.2  # error only on the interior rays
    pixels = np.flatnonzero(mask.ravel() > 0)
    budget = ErrorBudget()
    budget.add(pred, gt, mask, pixels, np.zeros(len(pixels), bool))
    s = budget.summary()
    shares = [s["classes"][c]["error_share"] for c in PIXEL_CLASSES if c != "background"]
    assert sum(shares) == pytest.approx(1.0)
    assert s["classes"]["inner"]["error_share"] == pytest.approx(1.0)
    assert s["masked_psnr"] == pytest.approx(10 * np.log10(1 / (0.04 * 64 / (24 * 24))), rel=1e-6)
