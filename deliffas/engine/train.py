"""The DELIFFAS training loop: full-image supervision, U-Nets once per frame, L1 then L1 + perceptual.

One iteration = one frame with K training cameras: the frame's temporal normal maps are encoded
once, every ray of the K images that meets the outer shell is shaded, and the loss compares the
images composited on black. Stage 1 is L1 only; stage 2 (from ``perceptual_start``) adds the
VGG-16 perceptual loss on the whole images (or 32x32 patches), weighted so both terms start with
the same magnitude (paper, appendix "Training Details"). Adam, lr 2e-4 with the official
exponential decay. Runs under ``torchrun`` with DistributedDataParallel (gloo on CPU, nccl on GPU).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Literal

import numpy as np
import torch
import torch.distributed as dist

from deliffas.engine.checkpointing import STATE_FILE, load_training_state, read_training_state, save_training_state
from deliffas.engine.rays import stack_rays
from deliffas.engine.samples import FrameSample, composite_target
from deliffas.engine.timing import StageTimer
from deliffas.models.deliffas import DeliffasModel, ModelConfig
from deliffas.models.zoo import config_from_dict, config_to_dict, get_config

__all__ = ["TrainConfig", "train", "train_step", "resolve_model_config", "render_sample_images", "TrainResult"]

logger = logging.getLogger(__name__)

PerceptualChoice = Literal["none", "vgg16-imagenet", "vgg16-random"]


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; written to ``RUN/train_config.json``."""

    shards: str
    """Directory of converted HDF5 shards (``deliffas convert``)."""
    out: str
    """Run directory (checkpoints, log.jsonl, previews)."""
    model: str = "two_surface"
    """Zoo name (``deliffas zoo list``)."""
    preset: str = "small"
    """Size preset of the zoo entry (``paper``, ``small``, ``tiny``)."""
    model_overrides: dict = field(default_factory=dict)
    """ModelConfig fields replacing the preset's (nested dicts for ``unet``/``mlp``)."""
    iters: int = 1000
    """Training iterations (one frame with ``cameras_per_frame`` images each)."""
    lr: float = 2e-4
    """Adam learning rate (paper)."""
    lr_decay_steps: int = 800_000
    """lr = lr · 0.1^(step / lr_decay_steps), as the official code."""
    cameras_per_frame: int = 4
    """K training cameras per iteration; the U-Nets run once for all K."""
    protocol: Literal["paper", "all"] = "paper"
    """Frames used: ``paper`` = every 10th frame (DELIFFAS), ``all`` = every converted frame."""
    perceptual: PerceptualChoice = "none"
    """Stage-2 perceptual backbone: ``vgg16-imagenet`` (weights must exist), ``vgg16-random``
    (the explicit offline option, seeded), or ``none`` (L1 only)."""
    perceptual_mode: Literal["image", "patch"] = "image"
    """Perceptual loss on whole images (paper) or on 32x32 patches (appendix ablation)."""
    perceptual_start: float = 0.6
    """Fraction of ``iters`` after which stage 2 (L1 + perceptual) starts."""
    perceptual_weight: float | None = None
    """Fixed weight of the perceptual term; None = balance it with L1 at the start of stage 2."""
    vgg16_path: str | None = None
    """ImageNet VGG-16 weight file for ``vgg16-imagenet`` (else env / torch hub cache)."""
    seed: int = 0
    device: str = "cpu"
    num_workers: int = 1
    """DataLoader workers (they also ray-cast the uv maps)."""
    ray_chunk: int | None = None
    """Rays per backward pass (single process): bounds the light-field activations of a step to
    this many rays; None = every ray of the step's K images in one graph (docs/reliability.md)."""
    checkpoint_every: int = 250
    preview_every: int = 250
    log_every: int = 10
    progress: bool = True


@dataclass(frozen=True)
class TrainResult:
    """What a finished run reports."""

    run_dir: Path
    iterations: int
    seconds: float
    last_loss: float
    iters_per_second: float
    stage_ms: dict[str, float]
    backbone: dict | None
    model: DeliffasModel | None = None


def resolve_model_config(cfg: TrainConfig, atlas_res: int, temporal_window: int) -> ModelConfig:
    """The zoo preset with the overrides applied and the data's atlas side and window."""
    base = config_to_dict(get_config(cfg.model, cfg.preset))
    for key, value in cfg.model_overrides.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            base[key] = {**base[key], **value}
        else:
            base[key] = value
    if base.get("atlas_res") != atlas_res:
        logger.info("model atlas_res %s -> %s (the shards' normal-map side)", base.get("atlas_res"), atlas_res)
    base["atlas_res"] = atlas_res
    base["temporal_window"] = temporal_window
    if isinstance(base.get("unet"), dict):
        base["unet"]["in_channels"] = 3 * (temporal_window + 1)
        base["unet"]["levels"] = base["unet"].get("levels")
        if base["unet"]["levels"] is not None:
            base["unet"]["levels"] = min(base["unet"]["levels"], int(math.log2(atlas_res)))
    return config_from_dict(ModelConfig, base)


def _lr_at(cfg: TrainConfig, step: int) -> float:
    return cfg.lr * 0.1 ** (step / cfg.lr_decay_steps)


def _model_inputs(model: DeliffasModel, sample: FrameSample, device: torch.device):
    """The model's inputs for a sample: normal_inner (1, C, S, S), normal_outer (or None for
    single-surface variants), the RayBatch of its cameras, and the per-ray ``shade`` arguments
    after ``batch_index`` (uv_inner, uv_outer, viewdir, inner_from_outer; None where the variant
    has no use for one)."""
    cfg = model.config
    two = cfg.uses_outer_surface
    ni = torch.from_numpy(sample.normal_inner)[None].to(device)
    no = torch.from_numpy(sample.normal_outer)[None].to(device) if two else None
    batch = stack_rays(sample.rays, [0] * sample.num_cameras).to(device)
    ray_args = (batch.uv_inner, batch.uv_outer if two else None, batch.viewdir if cfg.uses_viewdir else None,
                batch.inner_from_outer if two else None)
    return ni, no, batch, ray_args


def render_sample_images(model: DeliffasModel, sample: FrameSample, device: torch.device,
                         net: torch.nn.Module | None = None, timer: StageTimer | None = None,
                         chunk_size: int | None = None) -> torch.Tensor:
    """Images (K, H, W, 3) of the sample's cameras, background black; differentiable unless no_grad.

    ``net`` is the module called for the forward pass (the DDP wrapper during distributed
    training), by default the model itself. With a ``timer`` the stages are timed separately
    (``cnn`` encode, ``sample`` + ``mlp`` via the model's split methods when present).
    """
    net = net or model
    K = sample.num_cameras
    H, W = sample.images.shape[1:3]
    ni, no, batch, ray_args = _model_inputs(model, sample, device)
    if timer is None and chunk_size is None:
        pred = net(ni, no, batch.batch_index, *ray_args)
    else:
        timer = timer or StageTimer(device)
        with timer.stage("cnn"):
            features = model.encode(ni, no)
        with timer.stage("shade"):
            pred = model.shade_chunked(features, batch.batch_index, *ray_args, chunk_size=chunk_size or 262144)
    canvas = pred.new_zeros(K, H * W, 3)
    canvas = canvas.index_put((batch.image_index, batch.pixels), pred)
    return canvas.reshape(K, H, W, 3)


def _chunked_backward(model: DeliffasModel, sample: FrameSample, device: torch.device,
                      perceptual: torch.nn.Module | None, perceptual_weight: float,
                      generator: torch.Generator | None, ray_chunk: int) -> dict[str, float]:
    """Gradients of one step's loss, shading at most ``ray_chunk`` rays per graph (same gradient).

    The U-Nets run once and keep their graph; the light field's gradient w.r.t. the feature maps is
    accumulated chunk by chunk on detached copies and then pushed through the U-Nets in one
    backward. The perceptual term (a function of the whole images) is differentiated once w.r.t.
    the rendered images (rendered without a graph), and that image gradient enters each chunk's
    backward. Returns the loss terms and ``sq_sum`` (sum of squared errors over shaded values).
    """
    from deliffas.models.deliffas import FrameFeatures

    K = sample.num_cameras
    H, W = sample.images.shape[1:3]
    ni, no, batch, args = _model_inputs(model, sample, device)
    features = model.encode(ni, no)  # (1, C, S, S) maps with the U-Net graph
    leaves = FrameFeatures(inner=features.inner.detach().requires_grad_(),
                           outer=None if features.outer is None else features.outer.detach().requires_grad_())
    target = composite_target(sample.images, sample.masks).to(device)  # (K, H, W, 3)
    target_rays = target.reshape(K, H * W, 3)[batch.image_index, batch.pixels]  # (N, 3)
    n = batch.num_rays
    out: dict[str, float] = {}
    image_grad = None
    if perceptual is not None and perceptual_weight > 0:
        with torch.no_grad():
            pred_all = model.shade_chunked(leaves, batch.batch_index, *args, chunk_size=ray_chunk)
        canvas = pred_all.new_zeros(K, H * W, 3).index_put((batch.image_index, batch.pixels), pred_all)
        canvas = canvas.reshape(K, H, W, 3).requires_grad_()
        p = perceptual(canvas.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2),
                       torch.from_numpy(sample.masks).to(device), generator=generator)
        (perceptual_weight * p).backward()
        image_grad = canvas.grad.reshape(K, H * W, 3)[batch.image_index, batch.pixels]  # (N, 3)
        out["perceptual"] = float(p.detach())
        del canvas, pred_all
    l1_sum = sq_sum = 0.0
    for start in range(0, n, ray_chunk):
        sl = slice(start, start + ray_chunk)
        pred = model.shade(leaves, batch.batch_index[sl], *(None if a is None else a[sl] for a in args))
        diff = pred - target_rays[sl]
        l1_part = diff.abs().sum() / (3 * n)  # the mean over all shaded values, split into chunks
        chunk_loss = l1_part if image_grad is None else l1_part + (pred * image_grad[sl]).sum()
        chunk_loss.backward()
        l1_sum += float(l1_part.detach())
        sq_sum += float(diff.detach().square().sum())
    roots = [(f, leaf.grad) for f, leaf in ((features.inner, leaves.inner), (features.outer, leaves.outer))
             if f is not None and leaf.grad is not None]
    if roots:
        torch.autograd.backward([f for f, _ in roots], [g for _, g in roots])
    out.update(l1=l1_sum, loss=l1_sum + perceptual_weight * out.get("perceptual", 0.0), sq_sum=sq_sum)
    return out


def train_step(model: DeliffasModel, sample: FrameSample, optimizer: torch.optim.Optimizer, device: torch.device,
               perceptual: torch.nn.Module | None = None, perceptual_weight: float = 0.0,
               net: torch.nn.Module | None = None, generator: torch.Generator | None = None,
               ray_chunk: int | None = None) -> dict[str, float]:
    """One optimisation step on one frame; returns the loss terms and the step's PSNR (on shaded rays).

    ``ray_chunk`` bounds the rays shaded in one graph (single process only): the U-Nets run once,
    the light field chunk by chunk, and the gradient equals the unchunked one up to float
    summation order. Peak memory is then U-Nets + ``ray_chunk`` rays instead of every ray of the K
    images (docs/reliability.md).

    A sample whose cameras shade no ray at all (every camera looks away from the subject, or the
    outer shell lies outside every image) has no pixel that depends on a parameter, and the mean L1
    over zero rays would be NaN: the step is skipped (no optimizer step; ``skipped`` = 1, losses 0,
    ``psnr_rays`` NaN). Under DistributedDataParallel the rank still runs a zero-loss backward and
    steps with the other ranks' averaged gradients, so no collective hangs and the replicas stay equal.
    """
    ddp = isinstance(net, torch.nn.parallel.DistributedDataParallel)
    if ray_chunk is not None and (ray_chunk < 1 or ddp):
        raise ValueError(f"ray_chunk must be >= 1 and needs a single process (got {ray_chunk}, DDP {ddp})")
    num_rays = sum(r.num_rays for r in sample.rays)
    if num_rays == 0 and not ddp:
        optimizer.zero_grad(set_to_none=True)
        return {"l1": 0.0, "loss": 0.0, "psnr_rays": float("nan"), "skipped": 1.0}
    model.train()
    if ray_chunk is not None and num_rays > ray_chunk:
        optimizer.zero_grad(set_to_none=True)
        out = _chunked_backward(model, sample, device, perceptual, perceptual_weight, generator, ray_chunk)
        optimizer.step()
        mse = out.pop("sq_sum") / (3 * num_rays)
        out.update(skipped=0.0, psnr_rays=10 * math.log10(1.0 / mse) if mse > 0 else float("inf"))
        return out
    pred = render_sample_images(model, sample, device, net=net)  # (K, H, W, 3)
    target = composite_target(sample.images, sample.masks).to(device)
    K = sample.num_cameras
    shaded = torch.zeros(K, pred.shape[1] * pred.shape[2], dtype=torch.bool, device=device)
    for k, r in enumerate(sample.rays):
        shaded[k, torch.from_numpy(r.pixels).to(device)] = True
    shaded = shaded.reshape(K, pred.shape[1], pred.shape[2])
    # L1 over the rays the model paints (pixels outside the shell are background in both images,
    # up to person pixels the shell misses, which no parameter can change).
    if num_rays:
        l1 = (pred - target).abs()[shaded].mean()
    else:  # DDP only: a zero loss that reaches every parameter, so every gradient hook (all-reduce) fires
        l1 = pred.sum() * 0.0 + sum(p.sum() for p in model.parameters() if p.requires_grad) * 0.0
    loss = l1
    out = {"l1": float(l1.detach()), "skipped": 0.0 if num_rays else 1.0}
    if perceptual is not None and perceptual_weight > 0:
        p = perceptual(pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2),
                       torch.from_numpy(sample.masks).to(device), generator=generator)
        loss = loss + perceptual_weight * p
        out["perceptual"] = float(p.detach())
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    mse = float(((pred.detach() - target) ** 2)[shaded].mean()) if shaded.any() else float("nan")
    out["loss"] = float(loss.detach())
    out["psnr_rays"] = float("nan") if not num_rays else 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")
    return out


def _save_preview(path: Path, pred: torch.Tensor, sample: FrameSample) -> None:
    import cv2

    gt = composite_target(sample.images[:1], sample.masks[:1])[0].numpy()
    img = np.concatenate([pred[0].detach().cpu().numpy(), gt], axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    cv2.imwrite(str(tmp), cv2.cvtColor((img.clip(0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
    os.replace(tmp, path)


def _distributed() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend)
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _samples(cfg: TrainConfig, rank: int, world: int, start: int) -> tuple[Iterator[FrameSample], dict]:
    """Endless stream of training samples for this rank, and the data description."""
    from deliffas.engine.data_bridge import training_stream

    return training_stream(cfg, rank=rank, world=world, start_iteration=start)


def train(cfg: TrainConfig, resume: bool = False) -> TrainResult:
    """Train one model; resumable; distributed when launched by ``torchrun``.

    Writes into ``cfg.out``: ``train_config.json`` (resolved config, data and backbone record),
    ``log.jsonl`` (one record per ``log_every`` iterations), ``previews/iter_<n>.png`` (prediction |
    ground truth), ``checkpoint/`` (safetensors + JSON), ``optimizer.safetensors``, ``train_state.json``.
    """
    rank, world = _distributed()
    if cfg.ray_chunk is not None and world > 1:
        raise ValueError("ray_chunk needs a single process (under DDP every rank shades its rays in one graph)")
    device = torch.device(cfg.device if cfg.device != "cuda" or torch.cuda.is_available() else "cpu")
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    run = Path(cfg.out)
    run.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    if device.type == "cpu":
        # Leave the cores the DataLoader workers (and the other ranks) use: oversubscribed OpenMP
        # threads spin and made a step 30x slower on a 2-core machine.
        per_rank = max(1, (os.cpu_count() or 1) // world - cfg.num_workers)
        torch.set_num_threads(per_rank)
    start = 0
    state: dict[str, Any] = {}
    if resume and (run / STATE_FILE).is_file():
        start = read_training_state(run)["iteration"]
    stream, data_info = _samples(cfg, rank, world, start)
    model_cfg = resolve_model_config(cfg, data_info["atlas_res"], data_info["temporal_window"])
    model = DeliffasModel(model_cfg).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=(0.9, 0.999), eps=1e-7)
    if resume and (run / STATE_FILE).is_file():
        state = load_training_state(run, model, optimizer, device)
        logger.info("resuming %s at iteration %d", run, state["iteration"])
    net: torch.nn.Module = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    perceptual = None
    backbone = None
    if cfg.perceptual != "none":
        from deliffas.models.losses import PerceptualLoss

        perceptual = PerceptualLoss.from_source(cfg.perceptual, path=cfg.vgg16_path, seed=cfg.seed,
                                                mode=cfg.perceptual_mode).to(device)
        backbone = perceptual.record.to_dict() if perceptual.record else {"name": cfg.perceptual}
    if rank == 0:
        data_record = {k: v for k, v in data_info.items() if isinstance(v, (int, float, str, list)) and k != "cameras"}
        record = {"train": dataclasses.asdict(cfg), "model": config_to_dict(model_cfg), "data": data_record,
                  "perceptual_backbone": backbone, "world_size": world, "device": str(device),
                  "num_parameters": model.num_parameters()}
        (run / "train_config.json").write_text(json.dumps(record, indent=2, default=str) + "\n")
    stage2_at = int(cfg.perceptual_start * cfg.iters) if perceptual is not None else cfg.iters + 1
    perc_weight = state.get("perceptual_weight", cfg.perceptual_weight)
    gen = torch.Generator().manual_seed(cfg.seed + 7919 * rank)
    log = open(run / "log.jsonl", "a") if rank == 0 else None
    bar = None
    if rank == 0 and cfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.iters, initial=start, desc=f"train {cfg.model}", unit="it", dynamic_ncols=True)
    t0 = time.perf_counter()
    data_s = step_s = 0.0
    last = {"loss": float("nan")}
    it = start
    try:
        for it in range(start, cfg.iters):
            for group in optimizer.param_groups:
                group["lr"] = _lr_at(cfg, it)
            ta = time.perf_counter()
            sample = next(stream)
            tb = time.perf_counter()
            weight = 0.0
            if it >= stage2_at and perceptual is not None:
                if perc_weight is None and sum(r.num_rays for r in sample.rays) > 0:  # not on an empty view
                    perc_weight = _balance_weight(model, sample, device, perceptual)
                    logger.info("stage 2 at iteration %d: perceptual weight %.4g", it, perc_weight)
                weight = perc_weight or 0.0
            last = train_step(model, sample, optimizer, device, perceptual, weight, net=net, generator=gen,
                              ray_chunk=cfg.ray_chunk)
            tc = time.perf_counter()
            data_s += tb - ta
            step_s += tc - tb
            n_done = it + 1
            if log is not None and (n_done % cfg.log_every == 0 or n_done == cfg.iters):
                rec = {"iteration": n_done, **last, "lr": _lr_at(cfg, it), "stage": 2 if weight > 0 else 1,
                       "perceptual_weight": weight, "frame": sample.frame, "rays": int(sum(r.num_rays for r in sample.rays)),
                       "elapsed_s": time.perf_counter() - t0}
                log.write(json.dumps(rec) + "\n")
                log.flush()
            if rank == 0 and cfg.preview_every and (n_done % cfg.preview_every == 0 or n_done == cfg.iters):
                with torch.no_grad():
                    model.eval()
                    pred = render_sample_images(model, sample, device)
                _save_preview(run / "previews" / f"iter_{n_done:06d}.png", pred, sample)
            if rank == 0 and (n_done % cfg.checkpoint_every == 0 or n_done == cfg.iters):
                save_training_state(run, model, optimizer, {"iteration": n_done, "perceptual_weight": perc_weight,
                                                            "model": cfg.model, "preset": cfg.preset})
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr_rays']:.1f}")
    finally:
        if bar is not None:
            bar.close()
        if log is not None:
            log.close()
        if hasattr(stream, "close"):
            stream.close()
    done = max(it + 1 - start, 1)
    seconds = time.perf_counter() - t0
    result = TrainResult(run, it + 1, seconds, last["loss"], done / seconds,
                         {"data_ms": 1000 * data_s / done, "step_ms": 1000 * step_s / done}, backbone, model)
    if world > 1:
        dist.barrier()
    return result


def _balance_weight(model: DeliffasModel, sample: FrameSample, device: torch.device,
                    perceptual: torch.nn.Module) -> float:
    """Perceptual weight making both loss terms equally large on this frame (paper: 'roughly the same')."""
    with torch.no_grad():
        model.eval()
        pred = render_sample_images(model, sample, device)
        target = composite_target(sample.images, sample.masks).to(device)
        l1 = (pred - target).abs().mean()
        p = perceptual(pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2), torch.from_numpy(sample.masks).to(device),
                       generator=torch.Generator().manual_seed(0))
    return float(l1 / p.clamp_min(1e-12))
