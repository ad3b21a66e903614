"""Foreground image metrics: PSNR and SSIM inside the person's padded mask box, PSNR over mask pixels.

At small image sizes the official protocol's 600 x 496 crop (``deliffas.models.metrics``) is mostly
white background shared by prediction and ground truth, which lifts PSNR far above what the person's
pixels earn. Avatar papers report beside it metrics restricted to the person; these are they:

* **foreground box** (:func:`foreground_box`): the bounding box of ``mask > 0.5``, padded on every
  side by ``max(FG_MIN_PAD, FG_PAD_FRAC * longer box side)`` pixels, clipped to the image, grown to
  at least ``FG_MIN_SIDE`` (SSIM's window) where the image allows;
* **fg PSNR / fg SSIM**: PSNR and SSIM (scikit-image settings, as the official protocol) of the
  prediction *as rendered* against the ground truth over black (the training target, image x mask),
  both cropped to that box. The prediction is not masked: colour painted outside the person counts;
* **masked PSNR**: 10 log10(1 / MSE) over the pixels with ``mask > 0.5`` only (all channels).

Every function is ``(pred, gt, mask) -> float`` with pred, gt (3, H, W) in [0, 1] and mask (H, W)
in [0, 1]; a prediction of another size is resized to the ground truth's (bilinear).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from deliffas.models.image_metrics import mse, psnr, ssim

__all__ = ["FG_PAD_FRAC", "FG_MIN_PAD", "FG_MIN_SIDE", "align_prediction", "foreground_box", "foreground_pair", "fg_psnr", "fg_ssim",
           "masked_psnr"]

FG_PAD_FRAC = 0.1
"""Padding of the foreground box on each side, as a fraction of the box's longer side."""
FG_MIN_PAD = 4
"""Least padding of the foreground box on each side, in pixels."""
FG_MIN_SIDE = 16
"""Least side of the foreground box (SSIM needs 11 x 11), when the image is that large."""


def align_prediction(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Check pred, gt (3, H, W) and mask (H, W); the prediction resized to the GT size (bilinear) in its dtype."""
    if pred.dim() != 3 or pred.shape[0] != 3 or gt.dim() != 3 or gt.shape[0] != 3:
        raise ValueError(f"expected pred and gt of shape (3, H, W), got {tuple(pred.shape)}, {tuple(gt.shape)}")
    if tuple(mask.shape) != tuple(gt.shape[1:]):
        raise ValueError(f"mask: expected shape {tuple(gt.shape[1:])}, got {tuple(mask.shape)}")
    if pred.shape != gt.shape:
        pred = F.interpolate(pred[None], size=gt.shape[1:], mode="bilinear", align_corners=False)[0]
    return pred.to(gt.dtype)


def _grow(start: int, length: int, want: int, size: int) -> tuple[int, int]:
    """An interval of at least ``want`` (at most ``size``) containing [start, start + length), inside [0, size)."""
    want = min(max(length, want), size)
    start = start - (want - length) // 2
    return min(max(start, 0), size - want), want


def foreground_box(mask: torch.Tensor, pad_frac: float = FG_PAD_FRAC, min_pad: int = FG_MIN_PAD,
                   min_side: int = FG_MIN_SIDE) -> tuple[int, int, int, int]:
    """The padded bounding box of ``mask > 0.5``.

    Args:
        mask: (H, W) float in [0, 1] (or bool).
        pad_frac: padding per side = max(min_pad, round(pad_frac * longer box side)) pixels.
        min_pad: least padding per side, pixels.
        min_side: least side of the box (clipped to the image).

    Returns:
        (top, left, height, width); the whole image when the mask is empty.
    """
    if mask.dim() != 2:
        raise ValueError(f"mask: expected shape (H, W), got {tuple(mask.shape)}")
    height, width = mask.shape
    fg = mask.to(torch.float32) > 0.5
    if not fg.any():
        return 0, 0, int(height), int(width)
    rows = fg.any(dim=1).nonzero().squeeze(1)
    cols = fg.any(dim=0).nonzero().squeeze(1)
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    pad = max(int(min_pad), int(round(pad_frac * max(r1 - r0, c1 - c0))))
    r0, r1, c0, c1 = max(r0 - pad, 0), min(r1 + pad, height), max(c0 - pad, 0), min(c1 + pad, width)
    top, h = _grow(r0, r1 - r0, min_side, int(height))
    left, w = _grow(c0, c1 - c0, min_side, int(width))
    return top, left, h, w


def foreground_pair(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Prediction (as rendered) and ground truth (over black) cropped to the foreground box: (3, h, w) each."""
    pred = align_prediction(pred, gt, mask)
    top, left, h, w = foreground_box(mask)
    return pred[:, top : top + h, left : left + w], gt[:, top : top + h, left : left + w]


def fg_psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB) inside the padded foreground box; ``inf`` for identical crops."""
    return psnr(*foreground_pair(pred, gt, mask))


def fg_ssim(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float:
    """SSIM (scikit-image settings) inside the padded foreground box (needs a box of at least 11 x 11)."""
    return ssim(*foreground_pair(pred, gt, mask))


def masked_psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB) over the pixels with ``mask > 0.5`` (all channels); None-free: an empty mask gives ``nan``."""
    pred = align_prediction(pred, gt, mask)
    fg = mask.to(gt.device, torch.float32) > 0.5
    if not fg.any():
        return math.nan
    err = mse(pred[:, fg], gt[:, fg])
    return math.inf if err == 0.0 else 10.0 * math.log10(1.0 / err)
