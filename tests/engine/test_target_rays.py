"""The blocked CPU step composites only the rays' pixels: the same target values as the whole images'."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from deliffas.engine.data_bridge import evaluation_samples
from deliffas.engine.rays import stack_rays
from deliffas.engine.train_step import _target_rays, _targets


def test_target_rays_equal_the_composited_images_at_the_rays(tiny_shards):
    samples, _ = evaluation_samples(str(tiny_shards), "all", max_frames=1, with_rays=True, protocol="all")
    sample = next(iter(samples))
    rng = np.random.default_rng(0)
    masks = sample.masks * rng.uniform(0.2, 1.0, sample.masks.shape).astype(sample.masks.dtype)  # fractional edges
    sample = dataclasses.replace(sample, masks=masks)
    batch = stack_rays(sample.rays, [0] * sample.num_cameras)
    assert batch.num_rays > 0
    want = _targets(sample, batch, torch.device("cpu"))[1]
    assert torch.equal(_target_rays(sample, batch, torch.device("cpu")), want)
