"""Scalar image metrics on aligned image pairs: MSE, MAE, PSNR and SSIM (scikit-image's settings).

Pure functions of two (C, H, W) tensors in [0, 1], shared by the official protocol
(``deliffas.models.metrics``) and the foreground protocol (``deliffas.models.foreground``).
SSIM equals scikit-image ``structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1)`` over channel axis 0: Gaussian window sigma 1.5 truncated
at 3.5 sigma (11 x 11), K1 0.01, K2 0.03, population covariances, the SSIM map averaged over the
pixels at least 5 from the border, then over channels; float64.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["mse", "mae", "psnr", "ssim"]


def mse(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean squared error over all values (float64)."""
    return float(((pred.double() - gt.double()) ** 2).mean())


def mae(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean absolute error over all values (float64)."""
    return float((pred.double() - gt.double()).abs().mean())


def psnr(pred: torch.Tensor, gt: torch.Tensor, max_db: float | None = None) -> float:
    """PSNR = 10 log10(1 / MSE) of images in [0, 1].

    Identical images have MSE 0 and PSNR ``inf`` (the original's formula; an average including
    one is inf). Pass ``max_db`` to cap instead.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"psnr: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ")
    err = mse(pred, gt)
    value = math.inf if err == 0.0 else 10.0 * math.log10(1.0 / err)
    return value if max_db is None else min(value, max_db)


def _gaussian_window(sigma: float = 1.5, truncate: float = 3.5) -> torch.Tensor:
    """1-D Gaussian as ``scipy.ndimage.gaussian_filter1d``: radius int(truncate sigma + 0.5), float64."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def ssim(pred: torch.Tensor, gt: torch.Tensor, data_range: float = 1.0) -> float:
    """Mean SSIM equal to scikit-image's ``structural_similarity`` with ``gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=data_range`` over channel axis 0.

    Args:
        pred: (3, H, W) float, H and W >= 11.
        gt: (3, H, W) float.
        data_range: value range (1 for [0, 1] images).

    Returns:
        Mean over channels of the mean SSIM map (border of 5 pixels excluded).
    """
    if pred.shape != gt.shape or pred.dim() != 3:
        raise ValueError(f"ssim: expected two (C, H, W) images of equal shape, got {tuple(pred.shape)}, {tuple(gt.shape)}")
    window = _gaussian_window().to(pred.device)
    k = window.numel()
    if pred.shape[1] < k or pred.shape[2] < k:
        raise ValueError(f"ssim: images must be at least {k} x {k}, got {tuple(pred.shape)}")
    channels = pred.shape[0]
    wx = window.view(1, 1, 1, k).repeat(channels, 1, 1, 1)
    wy = window.view(1, 1, k, 1).repeat(channels, 1, 1, 1)

    def blur(z: torch.Tensor) -> torch.Tensor:  # valid separable filter: (1, C, H, W) -> (1, C, H-10, W-10)
        return F.conv2d(F.conv2d(z, wx, groups=channels), wy, groups=channels)

    x = pred.double()[None]
    y = gt.double()[None]
    ux, uy = blur(x), blur(y)
    vx = blur(x * x) - ux * ux
    vy = blur(y * y) - uy * uy
    vxy = blur(x * y) - ux * uy
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return float(s.mean(dim=(2, 3)).mean())


