"""``TrainConfig.rays_per_step``: each iteration trains on a random subset of its cameras' shaded rays."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from deliffas.engine.rays import CameraRays
from deliffas.engine.samples import FrameSample, subsample_rays
from deliffas.engine.train import TrainConfig, train


def _rays(n: int, width: int = 10, tensor: bool = False) -> CameraRays:
    pixels = np.arange(n, dtype=np.int64) * 3
    uv = np.stack([pixels / 100.0, pixels / 50.0], 1).astype(np.float32)
    fields = [pixels, uv, pixels % 2 == 0, uv + 1, np.ones((n, 3), np.float32)]
    if tensor:
        fields = [torch.from_numpy(f) for f in fields]
    return CameraRays(*fields, height=width, width=width)


def _sample(rays: list[CameraRays]) -> FrameSample:
    k = len(rays)
    return FrameSample(frame=0, images=np.zeros((k, 10, 10, 3), np.float32), masks=np.zeros((k, 10, 10), np.float32),
                       cameras=[], camera_ids=np.arange(k), normal_inner=np.zeros((3, 4, 4), np.float32),
                       normal_outer=np.zeros((3, 4, 4), np.float32), inner_verts=np.zeros((1, 3), np.float32),
                       outer_verts=np.zeros((1, 3), np.float32), rays=rays)


@pytest.mark.parametrize("tensor", [False, True])
def test_subsample_keeps_count_rays_with_their_fields_together(tensor):
    sample = _sample([_rays(30, tensor=tensor), _rays(10, tensor=tensor), _rays(0, tensor=tensor)])
    got = subsample_rays(sample, 12, np.random.default_rng(0))
    assert sum(r.num_rays for r in got.rays) == 12 and len(got.rays) == 3
    for r in got.rays:
        pixels = np.asarray(r.pixels)
        assert np.all(np.diff(pixels) > 0)  # each camera's kept rays stay in pixel order
        np.testing.assert_array_equal(np.asarray(r.uv_inner)[:, 0], (pixels / 100.0).astype(np.float32))
        np.testing.assert_array_equal(np.asarray(r.inner_from_outer), pixels % 2 == 0)
        assert type(r.pixels) is type(sample.rays[0].pixels)
    again = subsample_rays(sample, 12, np.random.default_rng(0))
    assert all(np.array_equal(np.asarray(a.pixels), np.asarray(b.pixels)) for a, b in zip(got.rays, again.rays))
    assert subsample_rays(sample, 40, np.random.default_rng(0)) is sample  # no more rays than asked: unchanged


def test_subsample_draws_uniformly_over_the_cameras():
    sample = _sample([_rays(3000), _rays(1000)])
    counts = np.array([[r.num_rays for r in subsample_rays(sample, 400, np.random.default_rng(s)).rays]
                       for s in range(50)])
    np.testing.assert_allclose(counts.mean(0), [300, 100], rtol=0.05)


@pytest.mark.parametrize("kw,match", [({"rays_per_step": 0}, "rays_per_step: expected"),
                                      ({"rays_per_step": -3}, "rays_per_step: expected"),
                                      ({"rays_per_step": 64, "perceptual": "vgg16-random"}, "compares whole images")])
def test_bad_rays_per_step_is_refused(tiny_shards, tmp_path, kw, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(shards=str(tiny_shards), out=str(tmp_path / "r"), **kw)


def test_a_perceptual_run_shades_every_ray_by_default(tiny_shards, tmp_path):
    from deliffas.engine.train_config import RAYS_PER_STEP

    base = dict(shards=str(tiny_shards), out=str(tmp_path / "r"))
    assert TrainConfig(**base).rays_per_step == RAYS_PER_STEP
    assert TrainConfig(**base, perceptual="vgg16-random").rays_per_step is None
    assert TrainConfig(**base, perceptual="vgg16-random", rays_per_step=None).rays_per_step is None


def test_a_run_trains_on_at_most_rays_per_step_rays(tiny_shards, tmp_path):
    cfg = TrainConfig(shards=str(tiny_shards), out=str(tmp_path / "r"), model="two_surface", preset="tiny", iters=4,
                      cameras_per_frame=2, protocol="all", num_workers=0, rays_per_step=50, log_every=1,
                      preview_every=0, progress=False)
    train(cfg)
    records = [json.loads(line) for line in (tmp_path / "r" / "log.jsonl").read_text().splitlines()]
    assert len(records) == 4 and all(0 < r["rays"] <= 50 for r in records)
    assert json.loads((tmp_path / "r" / "train_config.json").read_text())["train"]["rays_per_step"] == 50


def test_the_ray_caster_casts_about_the_budget_after_the_first_sample(tiny_shards, tmp_path):
    from deliffas.engine.data_bridge import RAY_MARGIN, training_stream

    full = TrainConfig(shards=str(tiny_shards), out=str(tmp_path / "r"), cameras_per_frame=2, protocol="all",
                       num_workers=0, seed=1, uv="raycast")
    stream, _ = training_stream(full, 2)
    everything = [sum(r.num_rays for r in next(stream).rays) for _ in range(6)]
    stream, _ = training_stream(dataclasses.replace(full, rays_per_step=40), 2)
    budgeted = [sum(r.num_rays for r in next(stream).rays) for _ in range(6)]
    assert budgeted[0] == everything[0] > 2 * RAY_MARGIN * 40  # the first sample sizes the share
    assert all(15 < n < 3 * RAY_MARGIN * 40 for n in budgeted[1:]), budgeted
    # the C rasteriser gives every shaded ray (a few times faster than casting the share); the step draws them
    stream, info = training_stream(dataclasses.replace(full, rays_per_step=40, uv="raster"), 2)
    assert info["uv"] == "raster" and [sum(r.num_rays for r in next(stream).rays) for _ in range(6)] == everything


def test_a_run_recorded_before_rays_per_step_resumes_with_every_ray(tiny_shards, tmp_path):
    from deliffas.engine.resume import resumed_config

    cfg = TrainConfig(shards=str(tiny_shards), out=str(tmp_path / "r"), model="two_surface", preset="tiny", iters=2,
                      cameras_per_frame=2, protocol="all", num_workers=0, preview_every=0, progress=False)
    train(cfg)
    path = tmp_path / "r" / "train_config.json"
    record = json.loads(path.read_text())
    assert record["train"].pop("rays_per_step") == 8192
    path.write_text(json.dumps(record))
    assert resumed_config(tmp_path / "r", {}).rays_per_step is None
