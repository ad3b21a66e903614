"""From converted shards to the engine's ``FrameSample`` stream (training) and sequence (evaluation).

The DataLoader workers read the shards and rasterise (or ray-cast) each item's cameras (``_ItemToSample``), so
geometry work overlaps with the model's forward/backward in the main process. With the torch uv source
(``TrainConfig.uv``) the workers only read, and :func:`with_torch_rays` rasterises the sample's cameras on the
model's device in the main process.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from typing import Iterator, Literal

import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler

from deliffas.data.dataset import FrameItem, RandomCameraSampler, ShardDataset
from deliffas.data.shards import ShardSet, open_shard_set
from deliffas.engine.config_fields import TEST_SPLITS
from deliffas.engine.rays import frame_rays, raster_frame_rays, torch_frame_rays, uv_source
from deliffas.engine.samples import FrameSample
from deliffas.geometry.atlas import UVAtlas

__all__ = ["training_stream", "evaluation_samples", "shard_info", "resolve_protocol", "validation_cameras",
           "with_torch_rays", "AUTO_PAPER_MIN_FRAMES", "EVAL_SPLITS", "TEST_SPLITS", "split_cameras", "run_protocol", "run_split_samples"]

logger = logging.getLogger(__name__)

AUTO_PAPER_MIN_FRAMES = 100
"""Protocol ``auto`` keeps every 10th frame (``paper``) from this many training frames on, else every frame."""
EVAL_SPLITS = ("validation", "novel_view", "novel_pose", "train")
"""What ``evaluate`` scores: ``validation`` = the run's validation cameras (training cameras it held out) on
the training frames; ``novel_view`` / ``novel_pose`` = the test splits (``TEST_SPLITS``); ``train`` = what it was fitted to."""


def resolve_protocol(shards_dir: ShardSet | str, requested: str) -> tuple[str, str]:
    """The frames protocol a run uses and the sentence that says so.

    ``paper`` keeps every 10th frame (DELIFFAS, for DynaCap-scale captures of thousands of frames),
    ``all`` every converted frame; ``auto`` is ``paper`` when the training sequence has at least
    ``AUTO_PAPER_MIN_FRAMES`` frames, else ``all``.
    """
    if requested not in ("auto", "paper", "all"):
        raise ValueError(f"protocol must be auto, paper or all, got {requested!r}")
    shards = open_shard_set(shards_dir)
    n = len(shards.frames("training")) if "training" in shards.meta.sequence_frames else 0
    if requested == "auto":
        chosen = "paper" if n >= AUTO_PAPER_MIN_FRAMES else "all"
        why = (f"{n} training frames >= {AUTO_PAPER_MIN_FRAMES}: every 10th frame (paper)" if chosen == "paper"
               else f"{n} training frames < {AUTO_PAPER_MIN_FRAMES}: every frame (all)")
        return chosen, f"frames protocol auto -> {chosen} ({why})"
    kept = -(-n // 10) if requested == "paper" else n
    return requested, f"frames protocol {requested}: {kept} of {n} training frames"


def validation_cameras(train_cameras: list[int], requested: int | tuple[int, ...] | list[int]) -> list[int]:
    """The training cameras held out for validation: ``requested`` calibration indices, or that many
    cameras evenly spaced over ``train_cameras``; at least one training camera must remain."""
    train = [int(c) for c in train_cameras]
    if isinstance(requested, int):
        if requested < 0:
            raise ValueError(f"validation cameras: expected a count >= 0, got {requested}")
        picks = [train[int((i + 0.5) * len(train) / requested)] for i in range(requested)] if requested else []
    else:
        picks = [int(c) for c in requested]
        bad = [c for c in picks if c not in train]
        if bad:
            raise ValueError(f"validation cameras {bad} are not training cameras (training cameras: {train})")
    if len(set(picks)) >= len(train):
        raise ValueError(f"validation cameras {picks} would leave no training camera (training cameras: {train})")
    return sorted(set(picks))


def split_cameras(split: str, record: dict, run: object = "the run") -> tuple[str, list[int] | None]:
    """The shards' split to read and the cameras to keep (None = the split's own) for evaluation ``split``
    of the run whose ``train_config.json`` is ``record``: ``validation`` is the training split's held-out cameras."""
    if split not in EVAL_SPLITS:
        raise ValueError(f"split must be one of {EVAL_SPLITS}, got {split!r}")
    if split != "validation":
        return split, None
    cameras = record.get("data", {}).get("validation_cameras") or []
    if not cameras:
        raise ValueError(f"{run}: the run holds out no validation cameras (train with --val-cameras N)")
    return "train", cameras


def run_protocol(record: dict, shards: ShardSet | str) -> str:
    """The frames protocol the run of ``record`` trained with (resolved ``auto`` as recorded, else resolved now)."""
    recorded = record.get("data", {}).get("protocol")
    if recorded in ("paper", "all"):
        return recorded
    return resolve_protocol(shards, record.get("train", {}).get("protocol", "paper"))[0]


def run_split_samples(shards: ShardSet | str, record: dict, split: str, max_frames: int | None = None,
                      with_rays: bool = False, temporal_window: int | None = None, run: object = "the run",
                      protocol: str | None = None) -> tuple[Iterator[FrameSample], dict]:
    """:func:`evaluation_samples` of evaluation ``split`` (``validation`` included) of the run whose
    ``train_config.json`` is ``record``, in ``protocol`` (None = the frames protocol it trained with)."""
    data_split, cameras = split_cameras(split, record, run)
    return evaluation_samples(shards, data_split, max_frames=max_frames, with_rays=with_rays,
                              protocol=protocol or run_protocol(record, shards), temporal_window=temporal_window,
                              cameras=cameras)


def shard_info(shards_dir: ShardSet | str, temporal_window: int | None = None) -> dict:
    """What the engine needs to know about a shard set (atlas, faces, window, cameras)."""
    shard_set = open_shard_set(shards_dir)
    meta = shard_set.meta
    stored = int(meta.attrs.get("window", 0))
    T = stored if temporal_window is None else min(int(temporal_window), stored)
    return {
        "shards": str(shard_set.out_dir),
        "atlas_res": meta.atlas_res,
        "temporal_window": T,
        "faces": np.asarray(meta.faces, dtype=np.int64),
        "atlas": UVAtlas(np.asarray(meta.uvs), np.asarray(meta.face_uvs)),
        "cameras": meta.cameras(),
        "train_cameras": [int(c) for c in meta.train_cameras],
        "test_cameras": [int(c) for c in meta.test_cameras],
        "num_verts": int(meta.rest_verts.shape[0]),
        "character": meta.attrs.get("character"),
    }


RAY_MARGIN = 1.5
"""With a ray budget, the share of pixels cast is sized for this many times the budget (the frames' and
cameras' shaded areas differ); the step keeps a uniform random ``rays_per_step`` of what comes back."""


class _ItemToSample:
    """collate_fn (batch size 1): FrameItem -> FrameSample, with the rays of the item's cameras from the C
    rasteriser (``rays="raster"``) or the ray caster (``rays="raycast"``), or none (``rays=None``).

    With a ``ray_budget`` (training with ``rays_per_step``) the ray caster casts only a random share of each
    camera's pixels, sized from the shaded rays of the previous sample (the first sample casts every pixel);
    the rasteriser, a few times faster, gives every shaded pixel."""

    def __init__(self, faces: np.ndarray, atlas: UVAtlas, cameras: list, rays: Literal["raster", "raycast"] | None,
                 ray_budget: int | None = None, seed: int = 0):
        self.faces, self.atlas, self.cameras, self.rays = faces, atlas, cameras, rays
        self.ray_budget, self.seed, self.calls = ray_budget, seed, 0
        self.full_rays: float | None = None  # shaded rays of the last sample's K cameras, all pixels cast

    def _cast(self, item: FrameItem, cams: list, inner: np.ndarray, outer: np.ndarray) -> list:
        if self.rays == "raster":
            return raster_frame_rays(inner, outer, self.faces, self.atlas, cams)
        if self.ray_budget is None:
            return frame_rays(inner, outer, self.faces, self.atlas, cams)
        fraction = 1.0 if not self.full_rays else min(1.0, RAY_MARGIN * self.ray_budget / self.full_rays)
        rng = np.random.default_rng([self.seed, int(item.frame), self.calls])
        self.calls += 1
        rays = frame_rays(inner, outer, self.faces, self.atlas, cams, fraction, rng)
        self.full_rays = sum(r.num_rays for r in rays) / fraction
        return rays

    def __call__(self, items: list[FrameItem]) -> FrameSample:
        (item,) = items
        ids = [int(c) for c in item.camera_ids]
        cams = [self.cameras[c] for c in ids]
        inner = item.inner_verts.numpy()
        outer = item.outer_verts.numpy()
        rays = self._cast(item, cams, inner, outer) if self.rays is not None else []
        return FrameSample(frame=int(item.frame), images=item.images.numpy().astype(np.float32) / 255,
                           masks=item.masks.numpy().astype(np.float32) / 255, cameras=cams, camera_ids=np.asarray(ids),
                           normal_inner=item.normal_maps_inner.numpy().astype(np.float32),
                           normal_outer=item.normal_maps_outer.numpy().astype(np.float32),
                           inner_verts=inner, outer_verts=outer, rays=rays)


def with_torch_rays(sample: FrameSample, faces: np.ndarray, atlas: UVAtlas, device: torch.device | str) -> FrameSample:
    """``sample`` with its cameras' rays rasterised by the torch rasteriser on ``device`` (tensors there)."""
    rays = torch_frame_rays(sample.inner_verts, sample.outer_verts, faces, atlas, sample.cameras, device)
    return dataclasses.replace(sample, rays=rays)


def _one_thread_worker(_worker_id: int) -> None:
    """DataLoader workers ray-cast and read shards: one torch thread each, no oversubscription."""
    torch.set_num_threads(1)


class _EndlessCameraSampler(Sampler):
    """``RandomCameraSampler`` epochs one after another, each with its own seed (rank- and resume-aware)."""

    def __init__(self, dataset: ShardDataset, k: int, seed: int):
        self.dataset, self.k, self.seed = dataset, k, seed

    def __iter__(self):
        for epoch in itertools.count():
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
            yield from RandomCameraSampler(self.dataset, self.k, g)


def training_stream(cfg, temporal_window: int, rank: int = 0, world: int = 1, start_iteration: int = 0,
                    shards: ShardSet | None = None) -> tuple[Iterator[FrameSample], dict]:
    """Endless training samples (one frame, ``cfg.cameras_per_frame`` random training cameras).

    Args:
        cfg: a ``TrainConfig``.
        temporal_window: T of the model being trained (its resolved config's, so the normal-map
            windows match its U-Nets' inputs); at most the window the shards store.
        rank: distributed rank (each rank draws its own frames).
        world: distributed size (number of ranks).
        start_iteration: iteration resumed from (changes the draw so a resumed run sees new samples).
        shards: ``cfg.shards`` opened by the caller (else opened here).
    """
    shards = open_shard_set(shards if shards is not None else cfg.shards)
    info = shard_info(shards, temporal_window)
    protocol, message = resolve_protocol(shards, getattr(cfg, "protocol", "paper"))
    if rank == 0:
        logger.info("%s", message)
    held_out = validation_cameras(info["train_cameras"], getattr(cfg, "validation_cameras", 0))
    fit_cameras = [c for c in info["train_cameras"] if c not in held_out]
    ds = ShardDataset(shards, split="train", cameras=fit_cameras, cameras_per_item=cfg.cameras_per_frame,
                      temporal_window=info["temporal_window"], protocol=protocol)
    if len(ds.frames) == 0:
        raise ValueError(f"{cfg.shards}: no training frames under protocol {protocol!r}")
    k = min(cfg.cameras_per_frame, len(ds.cameras))
    seed = cfg.seed + 7919 * rank + 104729 * start_iteration
    sampler = _EndlessCameraSampler(ds, k, seed=seed)
    source = uv_source(cfg.device, getattr(cfg, "uv", "auto"))
    collate = _ItemToSample(info["faces"], info["atlas"], info["cameras"], rays=None if source == "torch" else source,
                            ray_budget=getattr(cfg, "rays_per_step", None), seed=seed)
    workers = cfg.data_workers
    loader = DataLoader(ds, batch_size=1, sampler=sampler, collate_fn=collate, num_workers=workers,
                        persistent_workers=workers > 0, prefetch_factor=2 if workers > 0 else None,
                        worker_init_fn=_one_thread_worker if workers > 0 else None)
    info.update(train_frames=len(ds.frames), train_cameras=ds.cameras, protocol=ds.protocol, protocol_message=message,
                validation_cameras=held_out, uv=source)
    return iter(loader), info


def evaluation_samples(shards: ShardSet | str, split: str, max_frames: int | None = None, with_rays: bool = False,
                       protocol: str = "paper", temporal_window: int | None = None,
                       cameras: list[int] | None = None) -> tuple[Iterator[FrameSample], dict]:
    """Every camera of ``split`` (or the given calibration ``cameras``) for each of its frames (at most
    ``max_frames``, evenly spaced)."""
    shards = open_shard_set(shards)
    info = shard_info(shards, temporal_window)
    ds = ShardDataset(shards, split=split, cameras=cameras, cameras_per_item=None,
                      temporal_window=info["temporal_window"], protocol=protocol)
    frames = ds.frames
    if max_frames is not None and len(frames) > max_frames:
        pick = np.linspace(0, len(frames) - 1, max_frames).round().astype(int)
        ds = ShardDataset(shards, split=split, cameras=cameras, frames=[frames[i] for i in pick],
                          cameras_per_item=None, temporal_window=info["temporal_window"], protocol=protocol)
    collate = _ItemToSample(info["faces"], info["atlas"], info["cameras"], rays="raycast" if with_rays else None)
    return (collate([ds[i]]) for i in range(len(ds))), info
