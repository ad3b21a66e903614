"""Upper bounds on a run's held-out quality from the capture itself, before any model.

* :func:`aliasing_ceiling`: the same capture rendered twice, point-sampled (one ray per pixel, the
  recipe captures' default) and supersampled (what a camera integrating over its pixels sees):
  the masked PSNR of the supersampled targets (``composite_target`` of the straight colour and the
  coverage mask: each pixel's expected point sample over the black background) against the
  point-sampled ones is what a model that predicts each pixel's true average colour scores against
  point-sampled ground truth. Without sub-pixel geometry no model can predict which texel a point
  sample hits, so this bounds every model's score on such a capture.
* :func:`texture_oracle`: :class:`~deliffas.models.texel_oracle.TexelMeans` fitted on the training
  cameras' rays of every training frame (inner uv, or the outer shell's exit uv where the ray misses
  the inner surface) and scored on the training, validation and test cameras: what a static texture on
  the model's own uv mapping explains, atlas side by atlas side.

Both score the frames ``deliffas eval`` scores (``max_frames`` evenly spaced training frames) in
masked PSNR (the person's pixels, ``models.foreground.masked_psnr``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from deliffas.engine.data_bridge import run_split_samples
from deliffas.engine.identity import check_run_shards
from deliffas.engine.runs import read_run_record
from deliffas.engine.samples import composite_target
from deliffas.models.foreground import masked_psnr
from deliffas.models.texel_oracle import TexelMeans

__all__ = ["aliasing_ceiling", "texture_oracle", "HELD_OUT"]

HELD_OUT = ("validation", "novel_view")
"""The splits both bounds are scored on: the validation camera and the test cameras, training frames."""


def _score(pred: np.ndarray, target: torch.Tensor, mask: np.ndarray) -> float:
    """Masked PSNR of (H, W, 3) ``pred`` against the (H, W, 3) target."""
    return masked_psnr(torch.from_numpy(pred).permute(2, 0, 1).float(), target.permute(2, 0, 1).float(),
                       torch.from_numpy(np.asarray(mask)).float())


def _split_samples(shards, record: dict, split: str, max_frames: int | None, with_rays: bool = False):
    return run_split_samples(shards, record, split, max_frames, with_rays=with_rays)[0]


def aliasing_ceiling(run: str | Path, supersampled_shards: str | Path, max_frames: int | None = 10) -> dict:
    """Masked PSNR of ``supersampled_shards``' images against the run's own (point-sampled) shards.

    Returns ``{split: {"masked_psnr": mean over images, "images": n}}`` for ``HELD_OUT``.

    Raises:
        ValueError: the two shard sets differ in frames, cameras or image size.
    """
    record = read_run_record(run)
    point = check_run_shards(run, record, None)
    result = {}
    for split in HELD_OUT:
        scores = []
        for a, b in zip(_split_samples(point, record, split, max_frames),
                        _split_samples(str(supersampled_shards), record, split, max_frames), strict=True):
            if a.frame != b.frame or list(a.camera_ids) != list(b.camera_ids) or a.images.shape != b.images.shape:
                raise ValueError(f"{supersampled_shards}: frame {b.frame} cameras {list(b.camera_ids)} size "
                                 f"{b.images.shape[1:3]} differ from the run's shards (frame {a.frame}, cameras "
                                 f"{list(a.camera_ids)}, size {a.images.shape[1:3]}): not the same capture")
            gt, mean = composite_target(a.images, a.masks), composite_target(b.images, b.masks)
            scores += [_score(mean[k].numpy(), gt[k], a.masks[k]) for k in range(a.num_cameras)]
        result[split] = {"masked_psnr": float(np.mean(scores)), "images": len(scores)}
    return result


def texture_oracle(run: str | Path, sides: tuple[int, ...] = (256, 512, 1024), max_frames: int | None = 10) -> dict:
    """A static per-texel texture fitted on the run's training cameras, scored per split and atlas side.

    Returns ``{"train" | split: {side: masked PSNR}, "coverage": {side: fraction of texels met}}``
    (``train``: the training cameras at the evaluated frames, i.e. how well it fits at all).
    """
    record = read_run_record(run)
    shards = check_run_shards(run, record, None)
    oracle = TexelMeans(sides=tuple(sorted({64, 128, *sides})))
    for sample in _split_samples(shards, record, "train", None, with_rays=True):
        target = composite_target(sample.images, sample.masks)
        for k, rays in enumerate(sample.rays):
            colour = target[k].reshape(-1, 3)[torch.as_tensor(rays.pixels)].numpy()
            oracle.add(np.asarray(rays.uv_inner, np.float64), colour.astype(np.float64))
    result: dict = {"coverage": {side: oracle.coverage(side) for side in sides}}
    for split in ("train", *HELD_OUT):
        scores: dict[int, list[float]] = {side: [] for side in sides}
        for sample in _split_samples(shards, record, split, max_frames, with_rays=True):
            target = composite_target(sample.images, sample.masks)
            H, W = sample.images.shape[1:3]
            for k, rays in enumerate(sample.rays):
                for side in sides:
                    pred = np.zeros((H * W, 3))
                    pred[rays.pixels] = oracle.lookup(np.asarray(rays.uv_inner, np.float64), side)
                    scores[side].append(_score(pred.reshape(H, W, 3), target[k], sample.masks[k]))
        result[split] = {side: float(np.mean(v)) for side, v in scores.items()}
    return result
