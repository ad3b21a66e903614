"""Evaluation of a trained run: the official image metrics next to the per-stage timing.

Per test frame, the U-Net(s) run once (``cnn``); per test camera the uv maps come from the source
``EvalConfig.render_path.uv`` names (``deliffas.fast.uv_sources``) (``uv``), the features bilinearly sampled at
the hit uvs (``sample``) and the light-field MLP evaluated (``mlp``) — the paper's runtime breakdown.

Metrics (``deliffas.models.metrics``), each labelled with its protocol in the result: the official
protocol's PSNR/SSIM/FLIP (white composite, 600x496 crop; at small images mostly shared background)
and the ``foreground`` block (PSNR, SSIM, FLIP in the person's padded box, masked PSNR), which is the
headline. LPIPS and FID only from real weights (null with the reason otherwise); a clearly named
random-backbone substitute beside LPIPS. An evaluation of fewer than ``MIN_IMAGES_WARNING`` images
warns (``warnings`` in the result).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from deliffas.engine.devices import resolve_device
from deliffas.engine.config_fields import TEST_SPLITS
from deliffas.engine.eval_config import EvalConfig
from deliffas.engine.eval_result import EvalResult, ForegroundMetrics, OfficialMetrics
from deliffas.engine.data_bridge import run_protocol, run_split_samples
from deliffas.engine.identity import check_run_shards
from deliffas.io.infra.files import check_writable
from deliffas.engine.figures import GridImage, comparison_grid
from deliffas.engine.rays import uv_source
from deliffas.engine.runs import load_run
from deliffas.engine.samples import composite_target
from deliffas.engine.shading import render_frame
from deliffas.fast.frame import path_for_device
from deliffas.engine.timing import StageTimer
from deliffas.fast.config import RenderPathConfig
from deliffas.fast.shade import mlp_dtype
from deliffas.geometry.raycast import UVRaycaster
from deliffas.models.metrics import METRICS, Evaluator

__all__ = ["EvalConfig", "EvalResult", "evaluate", "MIN_IMAGES_WARNING", "HEADLINE"]

logger = logging.getLogger(__name__)

MIN_IMAGES_WARNING = 10
"""An evaluation over fewer images than this warns: its mean is too noisy to rank models."""
HEADLINE = "foreground.psnr"
"""The number tables, orderings and the demo lead with (``METRICS`` key)."""


def evaluate(cfg: EvalConfig) -> EvalResult:
    """Evaluate a run on a split; ``to_json()`` of the result is ``deliffas eval --json``."""
    device = resolve_device(cfg.device)
    if cfg.grid:
        check_writable(cfg.grid)  # before the work: a late failure would lose the metrics
    if cfg.save_images:
        check_writable(cfg.save_images, folder=True)
    model, record = load_run(cfg.run, device)
    shards = check_run_shards(cfg.run, record, cfg.shards)  # opened once for the whole command and passed down
    protocol = cfg.protocol or run_protocol(record, shards)
    samples, info = run_split_samples(shards, record, cfg.split, max_frames=cfg.max_frames,
                                      temporal_window=model.config.temporal_window, run=cfg.run, protocol=protocol)
    evaluator = Evaluator(vgg16_path=cfg.vgg16_path, lpips_path=cfg.lpips_path, inception_path=cfg.inception_path,
                          device=device)
    grid_rows: list[GridImage] = []
    timer = StageTimer(device)
    render_path = path_for_device(cfg.render_path, device)
    n_images = n_frames = 0
    cameras_seen: set[int] = set()
    t_wall = 0.0
    for i, sample in enumerate(samples):
        if i == 0:  # first use of open3d and of the model's kernels is slow; keep it out of the timing
            render_frame(model, sample, UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"]),
                         device, StageTimer(device), cfg.chunk_size, render_path)
        t0 = time.perf_counter()
        with timer.stage("scene"):
            raycaster = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
        preds = render_frame(model, sample, raycaster, device, timer, cfg.chunk_size, render_path)
        t_wall += time.perf_counter() - t0
        gt = composite_target(sample.images, sample.masks)  # black background
        for k in range(sample.num_cameras):
            scores = evaluator.add(preds[k].permute(2, 0, 1).cpu(), gt[k].permute(2, 0, 1),
                                   torch.from_numpy(sample.masks[k]))
            if cfg.grid and k == 0 and len(grid_rows) < cfg.grid_images:
                grid_rows.append(GridImage(gt[k].numpy(), preds[k].cpu().numpy(),
                                           f"cam {int(sample.camera_ids[k])} · frame {sample.frame} · "
                                           f"fg PSNR {scores.fg_psnr:.1f} dB"))
            if cfg.save_images:
                _save_white(Path(cfg.save_images), int(sample.camera_ids[k]), sample.frame, preds[k], sample.masks[k])
            cameras_seen.add(int(sample.camera_ids[k]))
        n_images += sample.num_cameras
        n_frames += 1
    if n_images == 0:
        raise ValueError(f"split {cfg.split!r} of {shards.out_dir} holds no frames/cameras to evaluate")
    summary = evaluator.summary()
    warnings = _few_images_warnings(n_images, protocol, cfg.split)
    if cfg.grid and grid_rows:
        comparison_grid(grid_rows, cfg.grid, f"{record.get('train', {}).get('model')} · {cfg.split}")
    stage_ms = _stage_ms(timer, n_images, n_frames)
    total_single = sum(stage_ms.values())
    return EvalResult(
        run=str(cfg.run), split=cfg.split, is_test_split=cfg.split in TEST_SPLITS, protocol=protocol,
        headline=HEADLINE, metric_protocols={m.key: m.protocol for m in METRICS},
        model=record.get("train", {}).get("model"), preset=record.get("train", {}).get("preset"),
        num_parameters=model.num_parameters(), frames=n_frames, cameras=tuple(sorted(cameras_seen)), images=n_images,
        resolution=(int(sample.images.shape[2]), int(sample.images.shape[1])),
        official=OfficialMetrics.from_summary(summary), foreground=ForegroundMetrics(**summary["foreground"]),
        warnings=tuple(warnings), grid=cfg.grid if cfg.grid and grid_rows else None, stage_ms=stage_ms,
        fps=1000.0 / total_single if total_single > 0 else None,
        fps_shared_cnn=n_images / t_wall if t_wall > 0 else None, device=str(device),
        uv=uv_source(device, render_path.uv, sample.images.shape[1] * sample.images.shape[2]),
        render_path=_path_name(render_path),
        perceptual_backbone=record.get("perceptual_backbone"))


def _path_name(cfg: RenderPathConfig) -> str:
    """``EvalResult.render_path``: ``plain``, or ``fast`` with how it shades."""
    return f"fast ({'fused fp32' if cfg.fused else mlp_dtype(cfg.dtype)})" if cfg.fast else "plain"


def _few_images_warnings(n_images: int, protocol: str, split: str) -> list[str]:
    """The result's warnings: one (also logged) when fewer than ``MIN_IMAGES_WARNING`` images were evaluated."""
    if n_images >= MIN_IMAGES_WARNING:
        return []
    warning = (f"only {n_images} image(s) evaluated (< {MIN_IMAGES_WARNING}): the means are noisy; "
               f"frames protocol {protocol!r}" + (", try --protocol all" if protocol == "paper" else ""))
    logger.warning("eval %s: %s", split, warning)
    return [warning]


def _stage_ms(timer: StageTimer, n_images: int, n_frames: int) -> dict[str, float]:
    """ms per image of each stage; the U-Net's per frame (shared by the frame's cameras; a single-view render
    pays it fully)."""
    per_image = timer.per_unit(n_images)
    return {"uv": per_image["uv"] + timer.total_ms.get("scene", 0.0) / n_images,
            "cnn": timer.total_ms.get("cnn", 0.0) / n_frames, "sample": per_image["sample"], "mlp": per_image["mlp"]}


def _save_white(root: Path, cam: int, frame: int, pred: torch.Tensor, mask: np.ndarray) -> None:
    import cv2

    img = pred.cpu().numpy()
    m = (mask > 0.5)[..., None]
    img = np.where(m, img, 1.0)
    path = root / f"{cam:03d}" / f"{frame:06d}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor((img.clip(0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
