"""What a training run is asked to do (:class:`TrainConfig`) and the model config it resolves to.

The model config is resolved once per run, in a fixed order, each step logged:
the zoo preset, then ``TrainConfig.model_overrides``, then what the shards impose (their atlas side,
and a temporal window no larger than the one they store). The data stream and the model are both
built from the result, so they agree on T.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from deliffas.engine.config_fields import device_field
from deliffas.fast.config import UVSource, check_uv_source, uv_field
from deliffas.models.model_table import DEFAULT_MODEL, DEFAULT_PRESET, PRESET_ROWS
from deliffas.options import (check_fields, count_or_indices, non_negative_float, non_negative_int,
                              open_unit_interval, opt, positive_float, positive_int, positive_int_or_all)

if TYPE_CHECKING:
    from deliffas.models.deliffas import DeliffasModel, ModelConfig

__all__ = ["TrainConfig", "TrainResult", "resolve_model_config"]

logger = logging.getLogger(__name__)

PerceptualChoice = Literal["none", "vgg16-imagenet", "vgg16-random"]

SCHEDULE_LR: dict[str, float] = {"hold-decay": 1.5e-3, "converge": 1e-3, "paper": 2e-4}
"""The peak learning rate of each ``TrainConfig.schedule`` when ``TrainConfig.lr`` is None."""

SCHEDULE_BETA2: dict[str, float] = {"hold-decay": 0.95, "converge": 0.999, "paper": 0.999}
"""Adam's beta2 of each ``TrainConfig.schedule`` when ``TrainConfig.adam_beta2`` is None."""


RAYS_PER_STEP = 8192
"""The default :attr:`TrainConfig.rays_per_step` of an L1 run."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; written to ``RUN/train_config.json``.

    ``time_budget``: after the first iterations (within the warm-up) the run plans ``iters`` from their speed,
    and plans again at the speed since, halfway through what is left, a few times (``engine.time_budget``); the
    ``hold-decay`` and ``converge`` schedules decay over the planned length. The plan replaces ``iters`` (and
    ``time_budget`` becomes None) in ``train_config.json``, whose ``time_budget`` entry records the plans: a
    resumed run continues to the last plan. Needs ``perceptual`` none.

    ``schedule``: each has its own peak rate and Adam beta2 (``SCHEDULE_LR``, ``SCHEDULE_BETA2``); ``paper`` is
    the official code's lr · 0.1^(step / lr_decay_steps).

    ``rays_per_step``: a uniform random subset of the K cameras' rays, drawn anew each iteration
    (:func:`deliffas.engine.samples.subsample_rays`); 8192, a quarter of a 256² step's rays, costs about 0.7x the
    step and learns as much per iteration (docs/results.md). A perceptual stage shades every ray (the loss compares
    whole images): the default becomes None there, another value is refused.

    ``ray_chunk``: None = every ray of the step's K images in one graph (docs/reliability.md).

    ``validation_cameras``: never trained on, never test cameras; ``eval --split validation`` scores them on the
    training frames, auto-capacity chooses on them.
    """

    shards: str = opt(help="folder written by 'deliffas convert'", flag="", nargs="?",
                      default_text="the run's, with --resume")
    out: str = opt(help="run directory (checkpoints, log.jsonl, previews)")
    model: str = opt(DEFAULT_MODEL, help="zoo name (deliffas zoo list); the paper's model: two_surface")
    preset: str = opt(DEFAULT_PRESET, help="size preset of the zoo entry (docs/models.md): "
                                           + " | ".join(r.name for r in PRESET_ROWS))
    model_overrides: dict = field(default_factory=dict)
    """ModelConfig fields replacing the preset's (nested dicts for ``unet``/``mlp``)."""
    iters: int = opt(5000, help="train to this iteration (with --resume: the run's, more extends it)",
                     parse=positive_int)
    time_budget: float | None = opt(None, help="train for about this many seconds instead of --iters: the "
                                          "iterations that fit, estimated from the speed of the first ones (L1 "
                                          "runs; the count is recorded in train_config.json)",
                                    parse=positive_float, metavar="SECONDS", default_text="--iters decides")
    schedule: Literal["hold-decay", "converge", "paper"] = opt(
        "hold-decay", help="learning-rate schedule: hold-decay = warm-up, the peak held, then a decay to a tenth over "
                           "the last 30 percent of the run's own --iters (Adam beta2 0.95); converge = warm-up, then a "
                           "decay to a tenth over the whole run (beta2 0.999); paper = the official Adam 2e-4 with "
                           "its decay over 800 k steps (GPU-days runs)")
    lr: float | None = opt(None, help="peak learning rate", parse=positive_float,
                           default_text="the schedule's, hold-decay 1.5e-3, converge 1e-3, paper 2e-4")
    adam_beta2: float | None = opt(None, help="Adam's beta2, the decay of its squared-gradient average",
                                   parse=open_unit_interval, default_text="the schedule's, hold-decay 0.95, else 0.999")
    lr_decay_steps: int = 800_000
    """``paper`` schedule: lr = lr · 0.1^(step / lr_decay_steps), as the official code."""
    warmup_iters: int = 50
    """``hold-decay`` and ``converge`` schedules: iterations of the linear warm-up from lr / warmup_iters to lr
    (at most a fifth of the run)."""
    lr_final: float = 0.1
    """``hold-decay`` and ``converge`` schedules: the learning rate at the last iteration, as a fraction of the peak."""
    decay_share: float = 0.3
    """``hold-decay`` schedule: the share of the iterations after the warm-up over which the rate decays (the
    peak is held before them)."""
    texture_lr_scale: float = 3.0
    """The texture atlases' learning rate as a multiple of the schedule's (``ModelConfig.texture_channels``):
    each texel sees the gradient of the few rays that sample it, so it may learn faster than the networks.
    The default pair (networks 1e-3, atlases 3e-3) was chosen on the validation camera over 3 seeds
    (docs/results.md): networks at 3e-3 leave two of three seeds with a third of the MLP's last layer dead."""
    cameras_per_frame: int = opt(3, help="training cameras per iteration; the U-Nets run once for all of them",
                                 parse=positive_int)
    rays_per_step: int | None = opt(RAYS_PER_STEP, help="train each iteration on at most this many of its "
                                                        "cameras' shaded rays, a random subset (the light-field "
                                                        "MLP's cost is per ray); all = every ray",
                                    parse=positive_int_or_all, metavar="N|all")
    protocol: Literal["auto", "paper", "all"] = opt("auto", help="frames used: paper = every 10th (DELIFFAS), "
                                                    "all = every frame, auto = paper from 100 training frames on, "
                                                    "else all; stated at start")
    validation_cameras: int | tuple[int, ...] = opt(0, help="training cameras held out as the validation split: a "
                                                    "count N or calibration indices (--auto-capacity holds out at "
                                                    "least 1)", flag="--val-cameras", parse=count_or_indices,
                                                    metavar="N|a,b,...")
    perceptual: PerceptualChoice = opt("none", help="stage-2 perceptual backbone: vgg16-imagenet (weights must "
                                                    "exist), vgg16-random (the explicit offline option, seeded), none "
                                                    "= L1 only")
    perceptual_mode: Literal["image", "patch"] = opt("image", help="perceptual loss on whole images (paper) or on "
                                                                   "32x32 patches (appendix ablation)")
    perceptual_start: float = 0.6
    """Fraction of ``iters`` after which stage 2 (L1 + perceptual) starts."""
    perceptual_weight: float | None = None
    """Fixed weight of the perceptual term; None = balance it with L1 at the start of stage 2."""
    saturation_weight: float = opt(0.01, help="weight of the penalty on U-Net feature logits beyond +-4, which "
                                              "keeps feature maps off the rails of their sigmoid; 0 = off",
                                   parse=non_negative_float)
    saturation_margin: float = 4.0
    """|logit| allowed without penalty (4: features within 0.018 of 0 or 1 are penalised)."""
    vgg16_path: str | None = opt(None, help="ImageNet VGG-16 weights (.pth/.safetensors) for --perceptual "
                                            "vgg16-imagenet",
                                 default_text="$DELIFFAS_VGG16_WEIGHTS or the torch hub cache")
    seed: int = opt(0, help="random seed of the model, the data order and the random backbone")
    device: str = device_field()
    num_workers: int | None = opt(None, help="DataLoader worker processes (they read the shards, and ray-cast with "
                                             "--uv raycast), 0 = in this process", flag="--workers",
                                  parse=non_negative_int,
                                  default_text="0 on a CPU device with 2 cores or fewer, else 1")
    uv: UVSource = uv_field()
    """Where the uv maps come from: ``raycast`` (open3d, where the samples are read: the DataLoader workers, or
    the training process with none), ``torch`` (the torch
    rasteriser on ``device``, in the main process), ``auto`` = ``torch`` on CUDA, else ``raycast``."""
    ray_chunk: int | None = opt(None, help="rays per backward pass (bounds training memory; single process)",
                                parse=positive_int, default_text="all rays at once")
    checkpoint_every: int = opt(250, help="save a checkpoint every N iterations, and at the last",
                                parse=positive_int)
    preview_every: int = opt(250, help="write previews/iter_N.png every N iterations, 0 = never",
                             parse=non_negative_int)
    log_every: int = 10
    progress: bool = True

    def __post_init__(self) -> None:
        """Refuse bad values when the run is described, before any work starts (ValueError naming the field)."""
        from deliffas.engine.devices import resolve_device  # local: the CLI reads this module without torch
        from deliffas.models.zoo import list_models, list_presets  # local: torch, as above

        if self.model not in list_models():
            raise ValueError(f"model: unknown {self.model!r}; the zoo has {', '.join(list_models())}")
        if self.preset not in list_presets(self.model):
            raise ValueError(f"preset: {self.model!r} has no preset {self.preset!r}; "
                             f"presets: {', '.join(list_presets(self.model))}")
        check_fields(self)  # every option's own check (its parse=, its Literal), as on the command line
        for name, minimum in (("log_every", 1), ("warmup_iters", 0), ("lr_decay_steps", 1)):  # not options
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
                raise ValueError(f"{name}: expected a whole number >= {minimum}, got {value!r}")
        if not (math.isfinite(self.saturation_margin) and self.saturation_margin > 0):
            raise ValueError(f"saturation_margin: expected a finite number > 0, got {self.saturation_margin!r}")
        if self.time_budget is not None and self.perceptual != "none":
            raise ValueError(f"time_budget: a run with a perceptual stage (perceptual {self.perceptual!r}) is "
                             "not sized by time, its stage-2 steps cost several times the first ones; give "
                             "--iters instead")
        if self.rays_per_step is not None and self.perceptual != "none":
            if self.rays_per_step != RAYS_PER_STEP:
                raise ValueError(f"rays_per_step: the perceptual loss (perceptual {self.perceptual!r}) compares whole "
                                 "images, every ray of them; leave --rays-per-step out or use --perceptual none")
            object.__setattr__(self, "rays_per_step", None)  # the default resolves to every ray
        if not (math.isfinite(self.texture_lr_scale) and self.texture_lr_scale > 0):
            raise ValueError(f"texture_lr_scale: expected a finite number > 0, got {self.texture_lr_scale!r}")
        if not (math.isfinite(self.lr_final) and 0 < self.lr_final <= 1):
            raise ValueError(f"lr_final: expected a number in (0, 1], got {self.lr_final!r}")
        if not (math.isfinite(self.decay_share) and 0 < self.decay_share <= 1):
            raise ValueError(f"decay_share: expected a number in (0, 1], got {self.decay_share!r}")
        check_uv_source(self.uv)  # resolved when the run starts: building a config compiles nothing
        resolve_device(self.device)  # --device cuda without CUDA: refused here, before any work

    @property
    def data_workers(self) -> int:
        """``num_workers``, or when None: 0 on a CPU device of a machine with 2 cores or fewer, else 1.

        A worker overlaps reading and ray casting with the step but takes a core from the step's threads; on
        2 cores the step at 2 threads plus the sample read in the same process is the faster iteration
        (docs/performance.md, "Training step")."""
        from deliffas.engine.devices import resolve_device  # local: the CLI reads this module without torch

        if self.num_workers is not None:
            return self.num_workers
        return 0 if resolve_device(self.device).type == "cpu" and (os.cpu_count() or 1) <= 2 else 1

    @property
    def peak_lr(self) -> float:
        """``lr``, or the schedule's default when None."""
        return SCHEDULE_LR[self.schedule] if self.lr is None else self.lr

    @property
    def beta2(self) -> float:
        """``adam_beta2``, or the schedule's when None."""
        return SCHEDULE_BETA2[self.schedule] if self.adam_beta2 is None else self.adam_beta2

    def lr_at(self, step: int) -> float:
        """The learning rate of 0-based iteration ``step`` under ``schedule``."""
        lr = self.peak_lr
        if self.schedule == "paper":
            return lr * 0.1 ** (step / self.lr_decay_steps)
        warmup = min(self.warmup_iters, self.iters // 5)
        if step < warmup:
            return lr * (step + 1) / warmup
        span = max(self.iters - 1 - warmup, 1)
        t = min(step - warmup, span) / span  # 0 after the warm-up, 1 at the last iteration
        if self.schedule == "hold-decay":
            hold = 1 - self.decay_share
            return lr if t < hold else lr * self.lr_final ** ((t - hold) / self.decay_share)
        return lr * self.lr_final ** t


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


def resolve_model_config(cfg: TrainConfig, atlas_res: int | None = None, data_window: int | None = None) -> ModelConfig:
    """The run's model config: the zoo preset, then the overrides, then what the shards impose.

    Args:
        cfg: the run (``model``, ``preset``, ``model_overrides``).
        atlas_res: the shards' normal-map side S (replaces the preset's); None = keep it.
        data_window: the largest temporal window the shards store; a larger requested T is
            reduced to it. None = keep the requested T.
    """
    from deliffas.models.deliffas import ModelConfig  # local: the CLI reads this module without torch
    from deliffas.models.checkpoint import config_from_dict, config_to_dict  # local: torch, as above
    from deliffas.models.zoo import get_config  # local: torch, as above

    base = config_to_dict(get_config(cfg.model, cfg.preset))
    logger.info("model config: zoo %r preset %r (atlas_res %s, temporal_window %s)", cfg.model, cfg.preset,
                base["atlas_res"], base["temporal_window"])
    for key, value in cfg.model_overrides.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            value = {**base[key], **value}
        logger.info("model config: override %s %r -> %r", key, base.get(key), value)
        base[key] = value
    if atlas_res is not None and base.get("atlas_res") != atlas_res:
        logger.info("model config: atlas_res %s -> %s (the shards' normal-map side)", base.get("atlas_res"), atlas_res)
        base["atlas_res"] = atlas_res
    if data_window is not None and base["temporal_window"] > data_window:
        logger.info("model config: temporal_window %s -> %s (the shards store no more)", base["temporal_window"],
                    data_window)
        base["temporal_window"] = data_window
    if isinstance(base.get("unet"), dict):
        unet = base["unet"]
        unet["in_channels"] = 3 * (base["temporal_window"] + 1)
        if unet.get("levels") is not None:
            unet["levels"] = min(unet["levels"], int(math.log2(base["atlas_res"] // base.get("unet_downsample", 1))))
    return config_from_dict(ModelConfig, base)
