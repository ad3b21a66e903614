"""Foreground protocol (deliffas.models.foreground) and the metric table: box, fg PSNR/SSIM, masked PSNR."""

from __future__ import annotations

import math

import pytest
import torch

from deliffas.models.foreground import fg_psnr, fg_ssim, foreground_box, foreground_pair, masked_psnr
from deliffas.models.metrics import METRICS, Evaluator, official_psnr


def _person(size: int = 96) -> tuple[torch.Tensor, torch.Tensor]:
    """A textured 'person' (30 x 18 px) over black in a size x size image, and its mask."""
    gen = torch.Generator().manual_seed(0)
    mask = torch.zeros(size, size)
    mask[40:70, 30:48] = 1
    gt = torch.rand(3, size, size, generator=gen) * mask
    return gt, mask


def test_foreground_box_pads_clips_and_grows():
    mask = torch.zeros(100, 80)
    mask[20:60, 10:30] = 1  # 40 x 20 box; pad = max(4, 0.1 * 40) = 4
    assert foreground_box(mask) == (16, 6, 48, 28)
    edge = torch.zeros(100, 80)
    edge[0:50, 70:80] = 1  # pad 5, clipped at the top and the right
    top, left, h, w = foreground_box(edge)
    assert top == 0 and left + w == 80 and h == 55 and w >= 15
    dot = torch.zeros(50, 50)
    dot[25, 25] = 1  # 1 px + 2 x 4 px pad = 9 < 16: grown to the SSIM-safe side
    assert foreground_box(dot)[2:] == (16, 16)
    assert foreground_box(torch.zeros(30, 20)) == (0, 0, 30, 20)
    with pytest.raises(ValueError, match="mask"):
        foreground_box(torch.zeros(3, 4, 5))


def test_blob_scores_high_officially_and_low_in_the_foreground():
    gt, mask = _person()
    blob = gt.sum(dim=(1, 2), keepdim=True) / mask.sum() * mask  # the person's mean colour, no texture
    official = official_psnr(blob, gt, mask)
    fg = fg_psnr(blob, gt, mask)
    assert official - fg > 5.0, (official, fg)  # the white crop is mostly shared background
    assert masked_psnr(blob, gt, mask) < fg  # the box also holds shared black margin
    assert fg_ssim(blob, gt, mask) < 0.5
    assert fg_psnr(gt, gt, mask) == math.inf and fg_ssim(gt, gt, mask) == pytest.approx(1.0)


def test_foreground_counts_colour_painted_outside_the_mask():
    gt, mask = _person()
    spill = gt.clone()
    spill[:, 36:40, 30:48] = 0.8  # just above the person, inside the padded box
    assert official_psnr(spill, gt, mask) == math.inf  # the official protocol masks the prediction too
    assert fg_psnr(spill, gt, mask) < 30 and masked_psnr(spill, gt, mask) == math.inf


def test_masked_psnr_is_over_mask_pixels_only():
    gt, mask = _person()
    pred = (gt + 0.1 * mask).clamp(0, 1)
    fg = mask > 0.5
    expected = 10 * math.log10(1 / float(((pred - gt)[:, fg] ** 2).mean()))
    assert masked_psnr(pred, gt, mask) == pytest.approx(expected)
    assert math.isnan(masked_psnr(pred, gt, torch.zeros_like(mask)))
    small = torch.nn.functional.interpolate(pred[None], size=(48, 48), mode="bilinear", align_corners=False)[0]
    assert foreground_pair(small, gt, mask)[0].shape == foreground_pair(pred, gt, mask)[0].shape


def test_metric_table_states_each_protocol():
    gt, mask = _person()
    keys = {m.key for m in METRICS}
    assert {"psnr", "ssim", "foreground.psnr", "foreground.ssim", "foreground.masked_psnr", "foreground.flip"} <= keys
    for m in METRICS:
        assert m.protocol.split(":")[0] in ("official", "foreground", "masked")
        value = m.fn(gt, gt, mask)
        assert value == (math.inf if m.higher_is_better and "psnr" in m.key else value)


def test_evaluator_summary_has_a_foreground_block(no_weights):
    gt, mask = _person()
    ev = Evaluator()
    r = ev.add((gt + 0.05).clamp(0, 1), gt, mask)
    s = ev.summary()
    assert s["protocol"].startswith("official") and s["foreground"]["protocol"].startswith("foreground")
    fg = s["foreground"]
    assert fg["psnr"] == pytest.approx(r.fg_psnr) and fg["masked_psnr"] == pytest.approx(r.masked_psnr)
    assert fg["lpips"] is None and fg["lpips_reason"]
    assert fg["flip"] is not None and 0 < fg["flip"] < 1 and s["flip"] is not None
    assert s["fid"] is None and s["fid_reason"]
