"""Training, resuming, evaluation, rendering and distributed training on a tiny capture."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from deliffas.engine.data_bridge import evaluation_samples
from deliffas.engine.evaluate import EvalConfig, evaluate
from deliffas.engine.render import RenderConfig, orbit_cameras, render_video
from deliffas.engine.train import TrainConfig, recorded_model_config, resolve_model_config, train, train_step
from deliffas.models import zoo
from deliffas.models.deliffas import DeliffasModel, ModelConfig
from deliffas.models.checkpoint import config_from_dict


def _cfg(shards, out, **kw):
    base = dict(shards=str(shards), out=str(out), model="two_surface", preset="tiny", iters=4, cameras_per_frame=2,
                protocol="all", num_workers=0, checkpoint_every=2, preview_every=2, log_every=1, progress=False)
    base.update(kw)
    return TrainConfig(**base)


def test_overfit_one_frame(tiny_shards):
    """A tiny two-surface model overfits one frame: the PSNR on its rays rises well above its start."""
    torch.manual_seed(0)
    samples, info = evaluation_samples(str(tiny_shards), "train", with_rays=True, protocol="all", temporal_window=2)
    sample = next(samples)
    cfg = resolve_model_config(_cfg(tiny_shards, "unused"), info["atlas_res"], 2)
    model = DeliffasModel(cfg)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = train_step(model, sample, opt, torch.device("cpu"))
    for _ in range(120):
        last = train_step(model, sample, opt, torch.device("cpu"))
    assert last["psnr_rays"] > first["psnr_rays"] + 8, (first, last)
    assert last["l1"] < 0.5 * first["l1"]


def test_train_step_with_frozen_feature_maps(tiny_shards):
    """With the U-Nets frozen (fine-tuning the light field only), the blocked step trains the MLP alone."""
    torch.manual_seed(0)
    samples, info = evaluation_samples(str(tiny_shards), "train", with_rays=True, protocol="all", temporal_window=2)
    sample = next(samples)
    model = DeliffasModel(resolve_model_config(_cfg(tiny_shards, "unused"), info["atlas_res"], 2))
    frozen = [p for name, p in model.named_parameters() if not name.startswith("mlp.")]
    for p in frozen:
        p.requires_grad_(False)
    before = [p.clone() for p in frozen]
    mlp_before = [p.clone() for p in model.mlp.parameters()]
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-3)
    assert np.isfinite(train_step(model, sample, opt, torch.device("cpu"), mlp_block=64)["loss"])
    assert all(torch.equal(a, b) for a, b in zip(before, frozen))
    assert any(not torch.equal(a, b) for a, b in zip(mlp_before, model.mlp.parameters()))


def test_train_resume_eval_render(tiny_shards, tmp_path):
    run = tmp_path / "run"
    res = train(_cfg(tiny_shards, run))
    assert res.iterations == 4
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2, 3, 4]
    assert all(np.isfinite(r["loss"]) for r in log)
    assert (run / "checkpoint" / "weights.safetensors").is_file()
    assert sorted(p.name for p in (run / "previews").iterdir()) == ["iter_000002.png", "iter_000004.png"]
    record = json.loads((run / "train_config.json").read_text())
    assert record["model"]["variant"] == "two_surface" and record["data"]["atlas_res"] == 32

    # resume continues from the saved iteration with the saved optimizer state
    res2 = train(_cfg(tiny_shards, run, iters=6), resume=True)
    assert res2.iterations == 6
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2, 3, 4, 5, 6]
    assert json.loads((run / "train_state.json").read_text())["iteration"] == 6

    result = evaluate(EvalConfig(run=str(run), split="novel_view", save_images=str(tmp_path / "pred"))).to_json()
    for key in ("psnr", "ssim", "lpips", "lpips_reason", "fid", "fid_reason", "fps", "stage_ms", "frames", "cameras"):
        assert key in result
    assert set(result["stage_ms"]) == {"uv", "cnn", "sample", "mlp"}
    assert all(v >= 0 for v in result["stage_ms"].values())
    assert result["cameras"] == [3] and result["frames"] == 6
    assert np.isfinite(result["psnr"]) and 0 < result["ssim"] <= 1
    if result["lpips"] is None:
        assert "not found" in result["lpips_reason"]
    assert result["fid"] is None and result["fid_reason"]
    assert len(list((tmp_path / "pred" / "003").glob("*.png"))) == 6
    json.dumps(result)  # JSON-ready

    video = render_video(RenderConfig(run=str(run), out=str(tmp_path / "frames"), frames=2))
    assert len(list(video.glob("*.png"))) == 2  # the capture's novel-pose motion has 2 frames


def test_resume_keeps_the_recorded_model(tiny_shards, tmp_path, monkeypatch):
    """A run resumed after its zoo preset changed (here: fewer U-Net levels) continues the model it recorded."""
    run = tmp_path / "run"
    train(_cfg(tiny_shards, run, iters=2))
    recorded = json.loads((run / "train_config.json").read_text())["model"]
    tiny = zoo.get_config("two_surface", "tiny")
    monkeypatch.setitem(zoo._REGISTRY["two_surface"], "tiny",
                        dataclasses.replace(tiny, unet=dataclasses.replace(tiny.unet, levels=3)))
    assert train(_cfg(tiny_shards, run, iters=3), resume=True).iterations == 3
    assert json.loads((run / "train_config.json").read_text())["model"] == recorded
    assert recorded_model_config(run) == config_from_dict(ModelConfig, recorded) == tiny


def test_cli_eval_json(tiny_shards, tmp_path):
    run = tmp_path / "run"
    train(_cfg(tiny_shards, run, model="single_surface_viewdir", iters=2))
    r = subprocess.run([sys.executable, "-m", "deliffas", "eval", str(run), "--split", "novel_pose", "--json"],
                       capture_output=True, text=True, check=True)
    result = json.loads(r.stdout.strip().splitlines()[-1])
    assert result["split"] == "novel_pose" and result["model"] == "single_surface_viewdir"
    assert result["lpips"] is None or isinstance(result["lpips"], float)


def test_orbit_cameras_look_at_subject():
    from deliffas.io.cameras import Camera

    ref = Camera("0", np.array([[100.0, 0, 32], [0, 100, 32], [0, 0, 1]]), np.eye(4), 64, 64)
    centers = np.zeros((8, 3)) + [0, 900, 0]
    for cam in orbit_cameras(ref, centers, 3000, 1500):
        pix, depth = cam.project(np.array([[0, 900.0, 0], [0, 1700.0, 0]]))
        np.testing.assert_allclose(pix[0], [32, 32], atol=1e-6)  # the centre projects to the principal point
        assert depth[0] > 0
        assert pix[1, 1] < pix[0, 1], "world up is image up"
        np.testing.assert_allclose(np.linalg.det(cam.R), 1.0, atol=1e-9)


def _weights_digest(model) -> str:
    h = hashlib.sha256()
    for k, v in sorted(model.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().cpu().numpy().tobytes())
    return h.hexdigest()


@pytest.mark.parametrize("length", ["iters=3", "time_budget=3.0"])
def test_ddp_two_gloo_processes(tiny_shards, tmp_path, length):
    """torchrun with 2 gloo processes runs a few steps; both ranks end with equal weights (with a time budget:
    rank 0's planned length on both)."""
    script = tmp_path / "ddp_train.py"
    script.write_text(textwrap.dedent(f"""
        import hashlib, os, sys
        import torch
        from deliffas.engine.train import TrainConfig, train
        cfg = TrainConfig(shards={str(tiny_shards)!r}, out={str(tmp_path / 'ddp_run')!r}, model="two_surface",
                          preset="tiny", {length}, cameras_per_frame=2, protocol="all", num_workers=0,
                          checkpoint_every=3, preview_every=0, progress=False)
        res = train(cfg)
        assert not torch.distributed.is_initialized()  # the group train() started is closed before exit
        h = hashlib.sha256()
        for k, v in sorted(res.model.state_dict().items()):
            h.update(k.encode()); h.update(v.detach().cpu().numpy().tobytes())
        rank = int(os.environ["RANK"])
        open(os.path.join({str(tmp_path)!r}, f"rank{{rank}}.sha"), "w").write(h.hexdigest())
    """))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
                        "29517", str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    h0, h1 = (tmp_path / "rank0.sha").read_text(), (tmp_path / "rank1.sha").read_text()
    assert h0 == h1
    record = json.loads((tmp_path / "ddp_run" / "train_config.json").read_text())
    assert record["world_size"] == 2
    if length.startswith("time_budget"):
        assert record["train"]["iters"] == record["time_budget"]["iterations"] >= 40
