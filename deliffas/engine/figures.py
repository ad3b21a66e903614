"""Comparison grids people can read: ground truth | prediction | error heat map with a colour bar.

One row per image, each panel at least ``MIN_PANEL_PX`` pixels on its shorter side (images of a
small capture are upsampled nearest-neighbour, so pixels stay pixels), labelled with the camera,
frame and the image's foreground PSNR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.engine.report import pyplot

__all__ = ["MIN_PANEL_PX", "ERROR_VMAX", "GridImage", "comparison_grid"]

MIN_PANEL_PX = 256
"""Least side of each panel in the written image, in pixels."""
ERROR_VMAX = 0.5
"""Top of the error colour scale (mean absolute error over RGB); fixed so grids compare across runs."""


@dataclass(frozen=True)
class GridImage:
    """One row of a grid."""

    gt: np.ndarray
    """(H, W, 3) float in [0, 1], ground truth over black (the training target)."""
    pred: np.ndarray
    """(H, W, 3) float in [0, 1], the prediction as rendered."""
    label: str
    """Row label, e.g. ``cam 3 · frame 12 · fg PSNR 21.4 dB``."""


def _upsample(img: np.ndarray, factor: int) -> np.ndarray:
    return np.repeat(np.repeat(img, factor, axis=0), factor, axis=1)


def comparison_grid(images: Sequence[GridImage], path: str | Path, title: str) -> Path:
    """Write a grid (one row per image: GT | prediction | |error| heat map with colour bar) to ``path``."""
    if not images:
        raise ValueError("comparison_grid: no images")
    plt = pyplot()
    h, w = images[0].gt.shape[:2]
    factor = max(1, math.ceil(MIN_PANEL_PX / min(h, w)))
    ph, pw = h * factor, w * factor
    dpi = 100
    fig_w = (3 * pw + 260) / dpi  # three panels, the colour bar and margins
    fig_h = (len(images) * (ph + 40) + 70) / dpi
    fig, axes = plt.subplots(len(images), 3, figsize=(fig_w, fig_h), dpi=dpi, squeeze=False)
    heat = None
    for row, im in zip(axes, images):
        err = np.abs(im.pred.astype(np.float64) - im.gt.astype(np.float64)).mean(axis=2)
        panels = ((im.gt, "ground truth"), (im.pred, "prediction"), (err, "|error| (mean over RGB)"))
        for ax, (data, name) in zip(row, panels):
            if data.ndim == 3:
                ax.imshow(_upsample(np.clip(data, 0, 1), factor), interpolation="nearest")
            else:
                heat = ax.imshow(_upsample(data, factor), cmap="inferno", vmin=0.0, vmax=ERROR_VMAX,
                                 interpolation="nearest")
            ax.set_title(name, fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(im.label, fontsize=8)
    fig.colorbar(heat, ax=axes[:, 2].tolist(), fraction=0.05, pad=0.02,
                 label=f"mean |error| (clipped at {ERROR_VMAX})")
    fig.suptitle(f"{title}  ({w}x{h} px, shown x{factor} nearest-neighbour)", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)  # not tight_layout: the colour bar axes are placed by colorbar
    plt.close(fig)
    return path
