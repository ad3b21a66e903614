"""The torch uv source: the same rays and the same training step as the ray caster's; train, eval and render
select it by device (forced here on the CPU) and need none of the CPU-only geometry packages."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from deliffas.engine.data_bridge import evaluation_samples, shard_info, with_torch_rays
from deliffas.engine.rays import RASTER_MAX_PIXELS_ON_GPU, raster_frame_rays, uv_source
from deliffas.fast.rasterize import raster_kernel_available
from deliffas.engine.train import TrainConfig, resolve_model_config, train_step
from deliffas.models.deliffas import DeliffasModel

BLOCKED = ("open3d", "pymeshlab", "xatlas", "pycolmap", "trimesh", "viser", "av", "flip_evaluator")
"""The packages a bare GPU box lacks (docs/performance.md, "GPU")."""


def _cfg(shards, out, **kw):
    base = dict(shards=str(shards), out=str(out), model="two_surface", preset="tiny", iters=2, cameras_per_frame=2,
                protocol="all", num_workers=0, checkpoint_every=2, preview_every=0, log_every=1, progress=False)
    base.update(kw)
    return TrainConfig(**base)


def test_uv_source_is_chosen_by_device(monkeypatch):
    import deliffas.fast.uv_sources as rays

    assert raster_kernel_available()  # a C compiler is part of the set-up: auto is the C rasteriser everywhere
    assert uv_source("cpu") == "raster" and uv_source("cuda") == "raster"
    big = RASTER_MAX_PIXELS_ON_GPU + 1  # an image rendered in the rendering process: the C rasteriser's one core
    assert uv_source("cuda", pixels=big) == "torch" and uv_source("cuda", pixels=256 * 256) == "raster"
    assert uv_source("cpu", pixels=big) == "raster" and uv_source("cuda", "raster", pixels=big) == "raster"
    monkeypatch.setattr(rays, "raster_kernel_available", lambda: False)  # no C compiler
    assert uv_source("cpu") == "raycast" and uv_source("cuda") == "torch" and uv_source("cuda:1") == "torch"
    assert uv_source("cpu", "torch") == "torch" and uv_source("cuda", "raycast") == "raycast"
    assert uv_source("cuda", "raster") == "raster"
    with pytest.raises(ValueError, match="uv: expected one of auto, raster, raycast, torch"):
        uv_source("cpu", "gpu")


def test_the_c_rasteriser_gives_the_ray_casters_rays(tiny_shards):
    samples, info = evaluation_samples(str(tiny_shards), "train", with_rays=True, protocol="all", temporal_window=2)
    cast = next(samples)
    raster = raster_frame_rays(cast.inner_verts, cast.outer_verts, info["faces"], info["atlas"], cast.cameras)
    for a, b in zip(cast.rays, raster):  # the same pixels (no pixel centre on an edge here), uvs to 1e-4
        np.testing.assert_array_equal(a.pixels, b.pixels)
        np.testing.assert_array_equal(a.inner_from_outer, b.inner_from_outer)
        np.testing.assert_allclose(a.uv_inner, b.uv_inner, atol=1e-4)
        np.testing.assert_allclose(a.uv_outer, b.uv_outer, atol=1e-4)
        np.testing.assert_allclose(a.viewdir, b.viewdir, atol=1e-6)


@pytest.mark.parametrize("model", ["two_surface", "single_surface_viewdir"])
def test_training_step_equals_the_ray_cast_one(tiny_shards, model):
    samples, info = evaluation_samples(str(tiny_shards), "train", with_rays=True, protocol="all", temporal_window=2)
    cast = next(samples)
    raster = with_torch_rays(cast, info["faces"], info["atlas"], "cpu")
    assert all(isinstance(r.pixels, torch.Tensor) for r in raster.rays)
    for a, b in zip(cast.rays, raster.rays):  # the same pixels (no pixel centre on an edge here), uvs to 1e-4
        np.testing.assert_array_equal(a.pixels, b.pixels.numpy())
        np.testing.assert_array_equal(a.inner_from_outer, b.inner_from_outer.numpy())
        np.testing.assert_allclose(a.uv_inner, b.uv_inner.numpy(), atol=1e-4)
        np.testing.assert_allclose(a.uv_outer, b.uv_outer.numpy(), atol=1e-4)
        np.testing.assert_allclose(a.viewdir, b.viewdir.numpy(), atol=1e-6)
    torch.manual_seed(0)
    cfg = resolve_model_config(_cfg(tiny_shards, "unused", model=model), info["atlas_res"], 2)
    m1 = DeliffasModel(cfg)
    m2 = copy.deepcopy(m1)
    out = []
    for m, sample in ((m1, cast), (m2, raster)):
        opt = torch.optim.SGD(m.parameters(), lr=0.05)
        out.append(train_step(m, sample, opt, torch.device("cpu")))
    assert out[0]["l1"] == pytest.approx(out[1]["l1"], rel=1e-4)
    assert out[0]["psnr_rays"] == pytest.approx(out[1]["psnr_rays"], rel=1e-4)
    for p1, p2 in zip(m1.parameters(), m2.parameters()):
        torch.testing.assert_close(p1, p2, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("uv", ["torch", "raster"])
def test_train_eval_render_without_the_cpu_geometry_packages(tiny_shards, tmp_path, uv):
    """In a fresh process with open3d, pymeshlab, xatlas, pycolmap, trimesh, viser, av and flip blocked: import
    deliffas and the train/eval/render path, train with the torch rasteriser or the C one (in a DataLoader
    worker), evaluate and render with it."""
    script = textwrap.dedent(f"""
        import json, sys
        for name in {BLOCKED!r}:
            sys.modules[name] = None
        import deliffas
        from deliffas.engine.evaluate import EvalConfig, evaluate
        from deliffas.engine.render import RenderConfig, render_video
        from deliffas.engine.train import TrainConfig, train
        from deliffas.fast.config import RenderPathConfig
        run = {str(tmp_path / "run")!r}
        cfg = TrainConfig(shards={str(tiny_shards)!r}, out=run, model="two_surface", preset="tiny", iters=2,
                          cameras_per_frame=2, protocol="all", num_workers=1, preview_every=1, progress=False,
                          uv={uv!r})
        res = train(cfg)
        ev = evaluate(EvalConfig(run=run, split="novel_view", render_path=RenderPathConfig(path="plain", uv={uv!r}),
                                 max_frames=2))
        video = render_video(RenderConfig(run=run, out={str(tmp_path / "frames")!r}, frames=2,
                                          render_path=RenderPathConfig(path="plain", uv={uv!r})))
        print(json.dumps({{"iterations": res.iterations, "psnr": ev.official.psnr, "uv": ev.uv,
                          "frames": len(list(video.glob("*.png"))), "blocked": sys.modules["open3d"] is None}}))
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (os.getcwd(), os.environ.get("PYTHONPATH")) if p)}
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got == {"iterations": 2, "psnr": got["psnr"], "uv": uv, "frames": 2, "blocked": True}
    assert np.isfinite(got["psnr"])
    record = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert record["data"]["uv"] == uv and record["train"]["uv"] == uv


def test_cli_passes_the_uv_source(tiny_shards, tmp_path):
    from deliffas.cli import build_parser
    from deliffas.cli.handlers import _train_config

    args = build_parser().parse_args(["train", str(tiny_shards), "--out", str(tmp_path / "r"), "--uv", "torch"])
    assert _train_config(args).uv == "torch"
    assert _train_config(build_parser().parse_args(["train", str(tiny_shards), "--out", str(tmp_path)])).uv == "auto"
    for cmd in (["eval", "RUN"], ["render", "RUN", "--out", str(tmp_path / "v.mp4")]):
        assert getattr(build_parser().parse_args([*cmd, "--uv", "raycast"]), "render_path.uv") == "raycast"
        with pytest.raises(SystemExit):
            build_parser().parse_args([*cmd, "--uv", "gpu"])


def test_configs_refuse_an_unknown_uv_source(tiny_shards, tmp_path, unchecked):
    from deliffas.engine.evaluate import EvalConfig
    from deliffas.engine.render import RenderConfig

    from deliffas.fast.config import RenderPathConfig

    for make in (lambda: RenderPathConfig(uv="gpu"), lambda: _cfg(tiny_shards, tmp_path, uv="gpu")):
        with unchecked(), pytest.raises(ValueError, match="uv: expected one of auto, raster, raycast, torch, got 'gpu'"):
            make()
