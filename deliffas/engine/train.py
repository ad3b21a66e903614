"""The DELIFFAS training loop: full-image supervision, U-Nets once per frame, L1 then L1 + perceptual.

One iteration = one frame with K training cameras: the frame's temporal normal maps are encoded
once, every ray of the K images that meets the outer shell is shaded, and the loss compares the
images composited on black (:mod:`deliffas.engine.train_step`). Stage 1 is L1 only; stage 2 (from
``perceptual_start``) adds the VGG-16 perceptual loss on the whole images (or 32x32 patches),
weighted so both terms start with the same magnitude (paper, appendix "Training Details"). Adam with the
schedule of ``TrainConfig.schedule`` (``hold-decay`` by default; ``paper`` is the official lr 2e-4 with
its exponential decay). Runs under ``torchrun`` with DistributedDataParallel
(gloo on CPU, nccl on GPU). :class:`Trainer` holds one run; :func:`train` runs it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from deliffas import environment
from deliffas.data.shards import ShardSet
from deliffas.engine.avatar import write_run_capture
from deliffas.engine.checkpointing import STATE_FILE, load_training_state, read_training_state, save_training_state
from deliffas.engine.data_bridge import shard_info, training_stream, with_torch_rays
from deliffas.engine.devices import cpu_threads, resolve_device
from deliffas.engine.identity import CAPTURE_KEYS, capture_identity, check_identity, shards_record
from deliffas.engine.runs import read_run_record
from deliffas.engine.samples import FrameSample, composite_target, subsample_rays
from deliffas.engine.time_budget import CALIBRATION, BudgetPlanner
from deliffas.engine.train_config import TrainConfig, TrainResult, resolve_model_config
from deliffas.engine.train_step import balance_weight, render_sample_images, train_step
from deliffas.models.deliffas import DeliffasModel, ModelConfig
from deliffas.models.losses import PerceptualLoss, SaturationTerm
from deliffas.io.infra.files import claim_output, write_bytes_atomic
from deliffas.models.checkpoint import config_from_dict, config_to_dict

__all__ = ["TrainConfig", "TrainResult", "Trainer", "train", "train_step", "resolve_model_config",
           "render_sample_images", "claim_run", "make_optimizer", "recorded_model_config", "RUN_MARKER"]

logger = logging.getLogger(__name__)

RUN_MARKER = "train_config.json"
"""The file every run writes first: a folder holding it is a deliffas run (``claim_run``)."""


def claim_run(run: Path, resume: bool, overwrite: bool) -> None:
    """Make ``run`` ready for training without ever replacing a user's work unasked.

    A missing or empty folder is created. A run (it holds ``RUN_MARKER``) is continued with ``resume``
    and replaced with ``overwrite``; any other non-empty folder is refused.

    Raises:
        FileExistsError: naming the folder and the option that would proceed.
    """
    if resume and (run / RUN_MARKER).is_file():
        return
    if run.is_dir() and any(run.iterdir()) and not overwrite:
        if (run / RUN_MARKER).is_file():
            raise FileExistsError(f"{run}: holds a training run; pass --resume to continue it or --overwrite to "
                                  "replace it")
        raise FileExistsError(f"{run}: not empty and not a training run (no {RUN_MARKER}); choose another --out")
    claim_output(run, overwrite, marker=RUN_MARKER, what="a training run")


def recorded_model_config(run: str | os.PathLike) -> ModelConfig | None:
    """The model configuration a run recorded in its ``train_config.json`` (None where it holds none)."""
    model = read_run_record(run).get("model")
    return config_from_dict(ModelConfig, model) if model else None


def _check_resumed_capture(run: Path, shards: str, found: dict) -> None:
    """A resumed run must continue on the capture it started on (the shards may have moved)."""
    path = run / RUN_MARKER
    try:
        recorded = json.loads(path.read_text()).get("identity")
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: corrupted JSON ({exc})") from None
    check_identity(recorded, f"the run {run}", found, f"the shards {shards}", CAPTURE_KEYS)


def make_optimizer(model: DeliffasModel, cfg: TrainConfig) -> torch.optim.Adam:
    """Adam (beta2 ``cfg.beta2``) over the model: the texture atlases in a group of their own at
    ``cfg.texture_lr_scale`` x the rate."""
    textures = {id(p) for p in model.texture_parameters()}
    groups = [{"params": [p for p in model.parameters() if id(p) not in textures], "lr_scale": 1.0}]
    if textures:
        groups.append({"params": model.texture_parameters(), "lr_scale": cfg.texture_lr_scale})
    # the fused kernel (CPU and CUDA) updates every tensor in one pass: 3x faster than the per-tensor loop
    fused = all(p.device.type in ("cpu", "cuda") for p in model.parameters())
    return torch.optim.Adam(groups, lr=cfg.peak_lr, betas=(0.9, cfg.beta2), eps=1e-7, fused=fused or None)


def _save_preview(path: Path, pred: torch.Tensor, sample: FrameSample) -> None:
    gt = composite_target(sample.images[:1], sample.masks[:1])[0].numpy()
    img = np.concatenate([pred[0].detach().cpu().numpy(), gt], axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    cv2.imwrite(str(tmp), cv2.cvtColor((img.clip(0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
    os.replace(tmp, path)


def _distributed() -> tuple[int, int, bool]:
    """(rank, world size, whether this call started the process group)."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), False
    if environment.world_size() > 1:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend)
        return dist.get_rank(), dist.get_world_size(), True
    return 0, 1, False


def _rank0_value(value: int) -> int:
    """Rank 0's ``value`` on every rank (a collective: every rank calls it at the same point)."""
    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def _device(cfg: TrainConfig, world: int) -> torch.device:
    device = resolve_device(cfg.device)
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", environment.local_rank())
    return device


class Trainer:
    """One training run: set up once (config, data, model, optimizer, resume), then step, preview
    and checkpoint. Writes into ``cfg.out``: ``train_config.json`` (resolved config, data and backbone
    record), ``log.jsonl`` (one record per ``log_every`` iterations), ``previews/iter_<n>.png``
    (prediction | ground truth), ``checkpoint/`` (safetensors + JSON), ``optimizer.safetensors``,
    ``train_state.json``.

    Args:
        cfg: the run.
        resume: continue from the run directory's last checkpoint when there is one (on the same capture).
        overwrite: replace an earlier run in ``cfg.out`` (see :func:`claim_run`).
    """

    def __init__(self, cfg: TrainConfig, resume: bool = False, overwrite: bool = False) -> None:
        self.created = time.perf_counter()  # a time_budget counts from here
        cfg = self.cfg = dataclasses.replace(cfg, shards=str(Path(cfg.shards).resolve()))  # found from any folder
        self.rank, self.world, self.owns_process_group = _distributed()
        if cfg.ray_chunk is not None and self.world > 1:
            raise ValueError("ray_chunk needs a single process (under DDP every rank shades its rays in one graph)")
        self.device = device = _device(cfg, self.world)
        self.run_dir = run = Path(cfg.out)
        if resume and (run / STATE_FILE).is_file():
            read_training_state(run)  # a broken state is named before anything else is read
        self.shards = ShardSet(cfg.shards)  # opened once for the whole command and passed down
        self.identity = capture_identity(self.shards.meta)
        if resume and (run / RUN_MARKER).is_file():
            _check_resumed_capture(run, cfg.shards, self.identity)
        if self.rank == 0:
            claim_run(run, resume, overwrite)
        if self.world > 1:
            dist.barrier()
        torch.manual_seed(cfg.seed)
        if device.type == "cpu":
            torch.set_num_threads(cpu_threads(self.world, cfg.data_workers))
        resuming = resume and (run / STATE_FILE).is_file()
        self.start = read_training_state(run)["iteration"] if resuming else 0
        stored = shard_info(self.shards)
        # a resumed run continues the model it recorded, whatever the zoo's preset has become since
        self.model_config = (recorded_model_config(run) if resuming else None) or resolve_model_config(
            cfg, stored["atlas_res"], stored["temporal_window"])
        self.stream, self.data_info = training_stream(cfg, self.model_config.temporal_window, rank=self.rank,
                                                      world=self.world, start_iteration=self.start, shards=self.shards)
        self.model = DeliffasModel(self.model_config).to(device)
        self.optimizer = make_optimizer(self.model, cfg)
        # the groups' rate multiples come from this run's config, not from a loaded state (a run saved
        # before the multiples existed has none)
        self.lr_scales = [group["lr_scale"] for group in self.optimizer.param_groups]
        state: dict[str, Any] = {}
        if resuming:
            state = load_training_state(run, self.model, self.optimizer, device)
            logger.info("resuming %s at iteration %d", run, state["iteration"])
        self.net: torch.nn.Module = self.model
        if self.world > 1:
            self.net = torch.nn.parallel.DistributedDataParallel(
                self.model, device_ids=[device.index] if device.type == "cuda" else None)
        self.perceptual: PerceptualLoss | None = None
        self.backbone: dict | None = None
        if cfg.perceptual != "none":
            self.perceptual = PerceptualLoss.from_source(cfg.perceptual, path=cfg.vgg16_path, seed=cfg.seed,
                                                         mode=cfg.perceptual_mode).to(device)
            self.backbone = self.perceptual.record.to_dict() if self.perceptual.record else {"name": cfg.perceptual}
        self.stage2_at = int(cfg.perceptual_start * cfg.iters) if self.perceptual is not None else cfg.iters + 1
        self.perceptual_weight: float | None = state.get("perceptual_weight", cfg.perceptual_weight)
        self.generator = torch.Generator().manual_seed(cfg.seed + 7919 * self.rank)
        self.saturation = (SaturationTerm(cfg.saturation_weight, cfg.saturation_margin)
                           if cfg.saturation_weight > 0 else None)
        self.planner: BudgetPlanner | None = None  # sizes a time_budget run (made when it runs)
        if self.rank == 0:
            self._write_record()
            write_run_capture(self.run_dir, self.shards)

    def _write_record(self) -> None:
        info = self.data_info
        data = {k: v for k, v in info.items() if isinstance(v, (int, float, str, list)) and k != "cameras"}
        record = {"train": {**dataclasses.asdict(self.cfg), **shards_record(self.run_dir, self.cfg.shards)},
                  "model": config_to_dict(self.model_config), "data": data,
                  "perceptual_backbone": self.backbone, "world_size": self.world, "device": str(self.device),
                  "num_parameters": self.model.num_parameters(), "identity": self.identity}
        if self.planner is not None and self.planner.plans:
            record["time_budget"] = self.planner.record()
        write_bytes_atomic(self.run_dir / RUN_MARKER, (json.dumps(record, indent=2, default=str) + "\n").encode())

    def _plan(self, n_done: int) -> bool:
        """After iteration ``n_done`` of a ``time_budget`` run: when :attr:`planner` plans now, set the run's length
        (rank 0's plan on every rank) and record it; True when it did."""
        planner = self.planner
        iters = planner.after(n_done, time.perf_counter(), _rank0_value if self.world > 1 else None)
        if iters is None:
            return False
        self.cfg = dataclasses.replace(self.cfg, iters=iters, time_budget=None)
        logger.info("time budget %.0f s: %d iterations (%.3f s each)", planner.seconds, iters,
                    planner.plans[-1]["seconds_per_iteration"])
        if self.rank == 0:
            self._write_record()
        return True

    def _stage_weight(self, it: int, sample: FrameSample) -> float:
        """The perceptual weight of iteration ``it``: 0 in stage 1, balanced once at the start of stage 2."""
        if it < self.stage2_at or self.perceptual is None:
            return 0.0
        if self.perceptual_weight is None and sum(r.num_rays for r in sample.rays) > 0:  # not on an empty view
            self.perceptual_weight = balance_weight(self.model, sample, self.device, self.perceptual)
            logger.info("stage 2 at iteration %d: perceptual weight %.4g", it, self.perceptual_weight)
        return self.perceptual_weight or 0.0

    def step(self, it: int) -> tuple[dict, FrameSample]:
        """Iteration ``it``: draw a sample, take one optimisation step; returns its log record and the sample."""
        lr = self.cfg.lr_at(it)
        for group, scale in zip(self.optimizer.param_groups, self.lr_scales):
            group["lr"] = lr * scale
        ta = time.perf_counter()
        sample = next(self.stream)
        if self.data_info["uv"] == "torch":  # rasterised here, on the model's device (no ray casting in the workers)
            sample = with_torch_rays(sample, self.data_info["faces"], self.data_info["atlas"], self.device)
        if self.cfg.rays_per_step is not None:  # L1 only (TrainConfig): no stage needs whole images
            sample = subsample_rays(sample, self.cfg.rays_per_step, np.random.default_rng([self.cfg.seed, it]))
        tb = time.perf_counter()
        weight = self._stage_weight(it, sample)
        out = train_step(self.model, sample, self.optimizer, self.device, self.perceptual, weight, net=self.net,
                         generator=self.generator, ray_chunk=self.cfg.ray_chunk, saturation=self.saturation)
        record = {"iteration": it + 1, **out, "lr": lr, "stage": 2 if weight > 0 else 1, "perceptual_weight": weight,
                  "frame": sample.frame, "rays": int(sum(r.num_rays for r in sample.rays)),
                  "data_s": tb - ta, "step_s": time.perf_counter() - tb}
        return record, sample

    def preview(self, n_done: int, sample: FrameSample) -> None:
        """Write ``previews/iter_<n_done>.png``: the first camera's prediction beside its ground truth."""
        with torch.no_grad():
            self.model.eval()
            pred = render_sample_images(self.model, sample, self.device)
        _save_preview(self.run_dir / "previews" / f"iter_{n_done:06d}.png", pred, sample)

    def checkpoint(self, n_done: int) -> None:
        """Save model, optimizer and training state after ``n_done`` iterations."""
        save_training_state(self.run_dir, self.model, self.optimizer,
                            {"iteration": n_done, "perceptual_weight": self.perceptual_weight, "model": self.cfg.model,
                             "preset": self.cfg.preset})

    def run(self) -> TrainResult:
        """Iterate from the start (or resumed) iteration to ``cfg.iters`` (with ``cfg.time_budget``: to the
        length it plans, ``engine.time_budget``); rank 0 logs, previews, checkpoints."""
        lead = self.rank == 0
        log = open(self.run_dir / "log.jsonl", "a") if lead else None
        if self.cfg.time_budget is not None:  # the loop runs at least to the first plan, whatever --iters says
            self.planner = BudgetPlanner(self.cfg.time_budget, self.created, self.start)
            self.cfg = dataclasses.replace(self.cfg, iters=max(self.cfg.iters, self.start + CALIBRATION))
        cfg = self.cfg
        bar = tqdm(total=cfg.iters, initial=self.start, desc=f"train {cfg.model}", unit="it",
                   dynamic_ncols=True) if lead and cfg.progress else None
        t0 = time.perf_counter()
        data_s = step_s = 0.0
        last = {"loss": float("nan")}
        it = n_done = saved = self.start
        try:
            while n_done < cfg.iters:
                it = n_done
                record, sample = self.step(it)
                data_s += record.pop("data_s")
                step_s += record.pop("step_s")
                last = record
                n_done = it + 1
                if self.planner is not None and self._plan(n_done):
                    cfg = self.cfg
                    if bar is not None:
                        bar.total = cfg.iters
                        bar.refresh()
                if log is not None and (n_done % cfg.log_every == 0 or n_done == cfg.iters):
                    log.write(json.dumps({**record, "elapsed_s": time.perf_counter() - t0}) + "\n")
                    log.flush()
                if lead and cfg.preview_every and (n_done % cfg.preview_every == 0 or n_done == cfg.iters):
                    self.preview(n_done, sample)
                if lead and (n_done % cfg.checkpoint_every == 0 or n_done == cfg.iters):
                    self.checkpoint(n_done)
                    saved = n_done
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{record['loss']:.4f}", psnr=f"{record['psnr_rays']:.1f}")
        except KeyboardInterrupt:  # keep every finished iteration: a checkpoint at the last one
            if lead and n_done > saved:
                self.checkpoint(n_done)
                logger.info("interrupted: checkpoint at iteration %d", n_done)
            raise
        finally:
            if bar is not None:
                bar.close()
            if log is not None:
                log.close()
            if hasattr(self.stream, "close"):
                self.stream.close()
        done = max(it + 1 - self.start, 1)
        seconds = time.perf_counter() - t0
        result = TrainResult(self.run_dir, it + 1, seconds, last["loss"], done / seconds,
                             {"data_ms": 1000 * data_s / done, "step_ms": 1000 * step_s / done}, self.backbone,
                             self.model)
        if self.world > 1:
            dist.barrier()
        return result


def train(cfg: TrainConfig, resume: bool = False, overwrite: bool = False) -> TrainResult:
    """Train one model; resumable; distributed when launched by ``torchrun`` (see :class:`Trainer`).

    ``cfg.out`` must be missing, empty, a run to continue (``resume``) or a run to replace (``overwrite``).
    """
    trainer = Trainer(cfg, resume, overwrite)
    try:
        return trainer.run()
    finally:
        # A process group left to interpreter exit can abort a rank as gloo's threads are torn down
        # ("terminate called without an active exception"): close the one this run started.
        if trainer.owns_process_group:
            dist.destroy_process_group()
