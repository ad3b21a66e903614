"""A trained run's error budget on a split: where its masked error sits (``models.error_budget``).

:func:`measure_error_budget` renders the split's images as ``evaluate`` does (reference path) and
accumulates an :class:`~deliffas.models.error_budget.ErrorBudget` from each prediction, its ground
truth and the rays that were shaded; :func:`budget_figure` draws the result.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from deliffas.engine.data_bridge import run_split_samples
from deliffas.engine.devices import resolve_device
from deliffas.engine.identity import check_run_shards
from deliffas.engine.runs import load_run
from deliffas.engine.shading import render_frame
from deliffas.engine.rays import camera_rays
from deliffas.engine.report import pyplot, save_figure
from deliffas.engine.samples import composite_target
from deliffas.engine.timing import StageTimer
from deliffas.geometry.raycast import UVRaycaster
from deliffas.models.error_budget import PIXEL_CLASSES, ErrorBudget

__all__ = ["measure_error_budget", "budget_figure"]


def measure_error_budget(run: str | Path, split: str = "validation", max_frames: int | None = 10,
                         device: str = "cpu") -> dict:
    """The error budget of ``run`` on ``split`` (``validation``, ``novel_view``, ``novel_pose``, ``train``).

    Returns ``ErrorBudget.summary()`` plus ``split`` and ``images``.
    """
    dev = resolve_device(device)
    model, record = load_run(run, dev)
    shards = check_run_shards(run, record, None)  # found as `eval` finds them (the run may have moved)
    samples, info = run_split_samples(shards, record, split, max_frames,
                                      temporal_window=model.config.temporal_window, run=run)
    budget = ErrorBudget()
    images = 0
    for sample in samples:
        raycaster = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
        preds = render_frame(model, sample, raycaster, dev, StageTimer(dev))
        gt = composite_target(sample.images, sample.masks).numpy()
        for k, cam in enumerate(sample.cameras):
            rays = camera_rays(raycaster, cam)
            budget.add(preds[k].cpu().numpy(), gt[k], sample.masks[k], rays.pixels, rays.inner_from_outer)
            images += 1
    return {"split": split, "images": images, **budget.summary()}


def budget_figure(budgets: dict[str, dict], path: str | Path, title: str = "error budget") -> Path:
    """Two panels per run: the masked squared error's share by pixel class, and by frequency band
    (error vs the ground truth's own energy). ``budgets``: run label -> ``measure_error_budget`` result."""
    plt = pyplot()
    fig, (ax_c, ax_b) = plt.subplots(1, 2, figsize=(11, 4), dpi=120)
    labels = list(budgets)
    width = 0.8 / max(len(labels), 1)
    classes = [c for c in PIXEL_CLASSES if c != "background"]
    for j, label in enumerate(labels):
        shares = [budgets[label]["classes"][c]["error_share"] or 0.0 for c in classes]
        ax_c.bar(np.arange(len(classes)) + j * width, shares, width, label=label)
        bands = budgets[label]["bands"]
        names = list(bands)
        ax_b.bar(np.arange(len(names)) + j * width, [bands[n]["error_ms"] for n in names], width, label=f"{label}: error")
    first = budgets[labels[0]]["bands"]
    ax_b.plot(np.arange(len(first)) + 0.4 - width / 2, [first[n]["gt_ms"] for n in first], "k.--",
              label="ground truth's energy")
    ax_c.set_xticks(np.arange(len(classes)) + 0.4 - width / 2, classes)
    ax_c.set_ylabel("share of the masked squared error")
    ax_c.set_title("by pixel class", fontsize=9)
    ax_b.set_xticks(np.arange(len(first)) + 0.4 - width / 2, list(first), rotation=12, fontsize=8)
    ax_b.set_yscale("log")
    ax_b.set_ylabel("mean square per value (interior)")
    ax_b.set_title("by detail scale (difference of Gaussians)", fontsize=9)
    for ax in (ax_c, ax_b):
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
