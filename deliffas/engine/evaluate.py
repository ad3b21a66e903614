"""Evaluation of a trained run: the official image metrics next to the per-stage timing.

Per test frame, the U-Net(s) run once (``cnn``); per test camera the uv maps are ray-cast
(``uv``), the features bilinearly sampled at the hit uvs (``sample``) and the light-field MLP
evaluated (``mlp``) — the paper's runtime breakdown. Metrics follow the official protocol
(``deliffas.models.metrics``): PSNR and SSIM always; LPIPS only from real weights and FID never
(both null with the reason); a clearly named random-backbone substitute beside them.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from deliffas.engine.data_bridge import evaluation_samples
from deliffas.engine.rays import camera_rays, paint_images, ray_query, stack_rays
from deliffas.engine.realtime import FastRender, fast_render_camera
from deliffas.engine.samples import FrameSample, composite_target
from deliffas.engine.timing import StageTimer
from deliffas.geometry.raycast import UVRaycaster
from deliffas.io.cameras import Camera
from deliffas.models.deliffas import DeliffasModel, FrameFeatures
from deliffas.models.metrics import Evaluator
from deliffas.models.unet import optimize_for_inference
from deliffas.models.zoo import load_checkpoint

__all__ = ["EvalConfig", "evaluate", "render_frame", "render_camera", "load_run"]

logger = logging.getLogger(__name__)

Split = Literal["novel_view", "novel_pose", "train"]


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate."""

    run: str
    """Run directory written by ``deliffas train``."""
    split: Split = "novel_view"
    """``novel_view``: held-out cameras on training-motion frames (every 10th); ``novel_pose``:
    the test motion; ``train``: training cameras (a sanity check)."""
    shards: str | None = None
    """Shard directory (default: the one the run was trained on)."""
    max_frames: int | None = None
    """Evaluate at most this many frames (evenly spaced); None = all of the split."""
    device: str = "cpu"
    chunk_size: int = 262144
    """Rays shaded at once (bounds peak memory for large images)."""
    save_images: str | None = None
    """Folder for predicted images ``<cam:03d>/<frame:06d>.png`` (white background), or None."""
    vgg16_path: str | None = None
    lpips_path: str | None = None
    fast: bool = False
    """Render by ``engine.realtime``'s CPU fast path (rasterised uvs, bf16 MLP where native) instead
    of the reference path, to measure what it changes."""


def load_run(run: str | Path, device: str | torch.device = "cpu") -> tuple[DeliffasModel, dict]:
    """The trained model (eval mode, U-Nets on their fused inference forward: ``optimize_for_inference``)
    and the run's recorded configuration."""
    run = Path(run)
    ckpt = load_checkpoint(run / "checkpoint", device)
    record = json.loads((run / "train_config.json").read_text()) if (run / "train_config.json").is_file() else {}
    return optimize_for_inference(ckpt.model.eval()), record


@torch.no_grad()
def render_frame(model: DeliffasModel, sample: FrameSample, raycaster, device: torch.device,
                 timer: StageTimer, chunk_size: int = 262144, fast: FastRender | None = None) -> torch.Tensor:
    """Render every camera of ``sample`` with per-stage timing; (K, H, W, 3) on black.

    ``sample.rays`` is ignored: the rays are cast here so the ``uv`` stage is timed.
    """
    with timer.stage("cnn"):
        features = model.encode(*sample.normal_maps(device))
    return torch.stack([render_camera(model, features, raycaster, cam, device, timer, chunk_size, fast)
                        for cam in sample.cameras])


@torch.no_grad()
def render_camera(model: DeliffasModel, features: FrameFeatures, raycaster, camera: Camera, device: torch.device,
                  timer: StageTimer, chunk_size: int = 262144, fast: FastRender | None = None) -> torch.Tensor:
    """One camera's (H, W, 3) image on black from the frame's encoded ``features`` (stages uv, sample, mlp);
    with ``fast`` on CPU, by ``engine.realtime`` (rasterised uvs, fused inputs, bf16 MLP where native)."""
    if fast is not None and torch.device(device).type == "cpu":
        return fast_render_camera(model, features, raycaster, camera, timer, fast)
    with timer.stage("uv"):
        batch = stack_rays([camera_rays(raycaster, camera)], [0]).to(device)
        query = ray_query(batch, model.spec)
    pred_parts = []
    for part in query.chunks(chunk_size):
        with timer.stage("sample"):
            encoded, feats = model.gather_inputs(features, part)
        with timer.stage("mlp"):
            pred_parts.append(model.mlp(encoded, feats))
    return paint_images(torch.cat(pred_parts), batch, 1, camera.height, camera.width)[0]


def evaluate(cfg: EvalConfig) -> dict:
    """Evaluate a run on a split; returns the JSON-ready result (see ``deliffas eval --json``)."""
    device = torch.device(cfg.device)
    model, record = load_run(cfg.run, device)
    shards = cfg.shards or record.get("train", {}).get("shards")
    if shards is None:
        raise ValueError(f"{cfg.run}: no shards recorded in train_config.json; pass --shards")
    protocol = record.get("train", {}).get("protocol", "paper")
    samples, info = evaluation_samples(shards, cfg.split, max_frames=cfg.max_frames, with_rays=False,
                                       protocol=protocol, temporal_window=model.config.temporal_window)
    evaluator = Evaluator(vgg16_path=cfg.vgg16_path, lpips_path=cfg.lpips_path, device=device)
    timer = StageTimer(device)
    fast = FastRender() if cfg.fast else None
    n_images = n_frames = 0
    cameras_seen: set[int] = set()
    t_wall = 0.0
    warmed = False
    for sample in samples:
        if not warmed:  # first use of open3d and of the model's kernels is slow; keep it out of the timing
            render_frame(model, sample, UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"]),
                         device, StageTimer(device), cfg.chunk_size, fast)
            warmed = True
        t0 = time.perf_counter()
        with timer.stage("scene"):
            raycaster = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
        preds = render_frame(model, sample, raycaster, device, timer, cfg.chunk_size, fast)
        t_wall += time.perf_counter() - t0
        gt = composite_target(sample.images, sample.masks)  # black background
        for k in range(sample.num_cameras):
            evaluator.add(preds[k].permute(2, 0, 1).cpu(), gt[k].permute(2, 0, 1), torch.from_numpy(sample.masks[k]))
            if cfg.save_images:
                _save_white(Path(cfg.save_images), int(sample.camera_ids[k]), sample.frame, preds[k], sample.masks[k])
            cameras_seen.add(int(sample.camera_ids[k]))
        n_images += sample.num_cameras
        n_frames += 1
    if n_images == 0:
        raise ValueError(f"split {cfg.split!r} of {shards} holds no frames/cameras to evaluate")
    summary = evaluator.summary()
    per_image = timer.per_unit(n_images)
    # The U-Net runs once per frame and is shared by the frame's cameras; a single-view render pays it fully.
    cnn_per_frame = timer.total_ms.get("cnn", 0.0) / n_frames
    stage_ms = {"uv": per_image["uv"] + timer.total_ms.get("scene", 0.0) / n_images, "cnn": cnn_per_frame,
                "sample": per_image["sample"], "mlp": per_image["mlp"]}
    total_single = sum(stage_ms.values())
    result = {
        "run": str(cfg.run),
        "split": cfg.split,
        "protocol": protocol,
        "model": record.get("train", {}).get("model"),
        "preset": record.get("train", {}).get("preset"),
        "num_parameters": model.num_parameters(),
        "frames": n_frames,
        "cameras": sorted(cameras_seen),
        "images": n_images,
        "resolution": [int(sample.images.shape[2]), int(sample.images.shape[1])],
        **{k: summary[k] for k in ("psnr", "ssim", "mse", "mae", "lpips", "lpips_reason", "fid", "fid_reason",
                                   "lpips_random_vgg16", "lpips_random_vgg16_backbone")},
        "stage_ms": stage_ms,
        "fps": 1000.0 / total_single if total_single > 0 else None,
        "fps_shared_cnn": n_images / t_wall if t_wall > 0 else None,
        "device": str(device),
        "render_path": f"fast ({fast.torch_dtype()})" if fast else "plain",
        "perceptual_backbone": record.get("perceptual_backbone"),
    }
    return result


def _save_white(root: Path, cam: int, frame: int, pred: torch.Tensor, mask: np.ndarray) -> None:
    import cv2

    img = pred.cpu().numpy()
    m = (mask > 0.5)[..., None]
    img = np.where(m, img, 1.0)
    path = root / f"{cam:03d}" / f"{frame:06d}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor((img.clip(0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
