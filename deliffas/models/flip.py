"""FLIP (NVIDIA, Andersson et al. 2020): a perceptual image difference calibrated on human data.

Unlike LPIPS and FID it needs no ImageNet network: its parameters ship with the ``flip-evaluator``
package (a compiled extension, no torch). LDR-FLIP at the package's default viewing condition
(67 pixels per degree) on sRGB images in [0, 1]; the mean of the per-pixel error map is reported,
0 = identical, 1 = the largest difference. Lower is better.

``flip_evaluator`` is imported when first used; when it is missing the metric is ``None`` with the
reason (:func:`flip_status`), never replaced.
"""

from __future__ import annotations

import numpy as np
import torch

from deliffas.optional import import_optional

__all__ = ["FLIP_PROTOCOL", "flip_status", "flip_error", "flip_map"]

FLIP_PROTOCOL = "LDR-FLIP (flip-evaluator, default 67 pixels per degree), mean of the error map; lower is better"


def _module():
    try:
        return import_optional("flip_evaluator", "FLIP needs the flip-evaluator package")  # a heavy extension
    except ImportError:
        return None


def flip_status() -> str | None:
    """None when FLIP can be computed, else the reason it cannot."""
    if _module() is None:
        return "FLIP needs the flip-evaluator package (pip install flip-evaluator); not installed"
    return None


def _hwc(x: torch.Tensor) -> np.ndarray:
    if x.dim() != 3 or x.shape[0] != 3:
        raise ValueError(f"flip: expected an image of shape (3, H, W), got {tuple(x.shape)}")
    return np.ascontiguousarray(x.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy(), dtype=np.float32)


def flip_map(pred: torch.Tensor, gt: torch.Tensor) -> np.ndarray:
    """Per-pixel LDR-FLIP error (H, W) float32 in [0, 1] of two (3, H, W) images in [0, 1].

    Raises:
        RuntimeError: flip-evaluator is not installed (see :func:`flip_status`).
    """
    flip = _module()
    if flip is None:
        raise RuntimeError(flip_status())
    if pred.shape != gt.shape:
        raise ValueError(f"flip: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ")
    error_map, _, _ = flip.evaluate(_hwc(gt), _hwc(pred), "LDR", applyMagma=False)
    return np.asarray(error_map, dtype=np.float32).reshape(gt.shape[1:])


def flip_error(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Mean LDR-FLIP error of two (3, H, W) images in [0, 1] (lower is better; 0 = identical).

    ``mask`` is accepted for the metric signature ``(pred, gt, mask)`` and not used: crop first
    (``deliffas.models.foreground.foreground_pair``) to score the person.
    """
    return float(flip_map(pred, gt).mean())
