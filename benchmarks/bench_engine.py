"""End-to-end frame time against the sum of its stages, and training speed of the small preset at 256^2 (smoke mode:
the smoke bench capture, 64 x 96 for 940 x 1285, two rounds)."""

from __future__ import annotations

import dataclasses
import time

import torch

from benchmarks._capture import bench_capture
from benchmarks._timing import BENCH_THREADS, torch_threads
from benchmarks.common import Result, sized
from deliffas.models.unet import optimize_for_inference


def _sample(shards, K: int = 4):
    from deliffas.engine.data_bridge import evaluation_samples

    samples, info = evaluation_samples(str(shards), "all", max_frames=1, with_rays=True, protocol="all",
                                       temporal_window=2)
    s = next(samples)
    keep = list(range(min(K, s.num_cameras)))
    s = dataclasses.replace(s, images=s.images[keep], masks=s.masks[keep], cameras=[s.cameras[i] for i in keep],
                            camera_ids=s.camera_ids[keep], rays=[s.rays[i] for i in keep])
    return s, info


def _model(info, variant: str = "two_surface"):
    from deliffas.engine.train import TrainConfig, resolve_model_config
    from deliffas.models.deliffas import DeliffasModel

    cfg = resolve_model_config(TrainConfig(shards="", out="", model=variant, preset="small"), info["atlas_res"], 2)
    return DeliffasModel(cfg)


def _end_to_end(model, sample, info, camera, label: str) -> list[Result]:
    from deliffas.engine.shading import render_frame
    from deliffas.engine.timing import StageTimer
    from deliffas.geometry.raycast import UVRaycaster

    s1 = dataclasses.replace(sample, cameras=[camera], images=sample.images[:1], masks=sample.masks[:1])
    device = torch.device("cpu")
    best_wall, best_stages = float("inf"), None
    for i in range(sized(4, 2)):
        timer = StageTimer(device)
        t0 = time.perf_counter()
        with timer.stage("uv"):
            rc = UVRaycaster(s1.inner_verts, info["faces"], s1.outer_verts, info["atlas"])
        render_frame(model, s1, rc, device, timer, chunk_size=65536)
        wall = time.perf_counter() - t0
        if i and wall < best_wall:  # first call warms up open3d and the kernels
            best_wall, best_stages = wall, dict(timer.total_ms)
    stage_sum = sum(best_stages.values()) / 1000
    return [Result("e2e", f"frame {label}: wall time", best_wall * 1000, "ms",
                   note=", ".join(f"{k} {v:.1f}" for k, v in best_stages.items())),
            Result("e2e", f"frame {label}: wall / sum of stages", best_wall / stage_sum, "ratio",
                   baseline="sum of stages", ratio=best_wall / stage_sum, target="<= 1.2",
                   passed=best_wall / stage_sum <= 1.2)]


def _frame_memory(shards, chunk: int) -> list[Result]:
    """Peak memory of a 940 x 1285 frame (fresh process, see benchmarks/_frame_memory.py) against its bound."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    from deliffas.engine.memory import MIB, PEAK_PROBE_ENV

    if not Path("/proc/self/clear_refs").exists():
        return [Result("e2e", "skipped: peak memory needs Linux /proc/self/clear_refs", 0.0, "")]
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, **PEAK_PROBE_ENV, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    res = subprocess.run([sys.executable, "-m", "benchmarks._frame_memory", str(shards), str(chunk)],
                         capture_output=True, text=True, env=env, cwd=root, timeout=600)
    if res.returncode != 0:
        raise RuntimeError(f"benchmarks._frame_memory failed:\n{res.stderr[-2000:]}")
    m = json.loads(res.stdout.strip().splitlines()[-1])
    formula = (f"2 F + 320 B P + 4 KiB c + 64 B N + 16 MiB with F {m['features_bytes'] / MIB:.0f} MiB (paper widths, "
               f"S = {m['atlas_res']}), P {m['pixels']}, c {chunk}, N {m['rays']}")
    size = f"{m['height']}x{m['width']}"
    return [Result("e2e", f"frame {size}: peak memory growth, chunk {chunk}", m["chunked"] / MIB, "MiB",
                   baseline="stated bound (docs/reliability.md)", ratio=m["chunked"] / m["bound"],
                   target=f"<= bound {m['bound'] / MIB:.0f} MiB", passed=m["chunked"] <= m["bound"], note=formula),
            Result("e2e", f"frame {size}: peak memory growth, chunk_size = all {m['rays']} rays", m["unchunked"] / MIB,
                   "MiB", note="sampling of every ray at once; the MLP still runs in INFERENCE_CHUNK row blocks")]


def _train_step(model, opt, sample, shared: bool):
    """One training step as a function of a StageTimer; ``shared`` encodes once per frame, else once per camera."""
    from deliffas.engine.rays import ray_query, stack_rays
    from deliffas.engine.samples import composite_target

    K = sample.num_cameras
    H, W = sample.images.shape[1:3]
    target = composite_target(sample.images, sample.masks)
    ni = torch.from_numpy(sample.normal_inner)[None]
    no = torch.from_numpy(sample.normal_outer)[None]
    groups = [list(range(K))] if shared else [[k] for k in range(K)]
    batches = [stack_rays([sample.rays[k] for k in g], [0] * len(g)) for g in groups]
    queries = [ray_query(batch, model.spec) for batch in batches]

    def step(timer) -> None:
        loss = 0.0
        with timer.stage("total"):
            for g, batch, query in zip(groups, batches, queries):
                with timer.stage("cnn"):
                    feats = model.encode(ni, no)
                with timer.stage("sample"):
                    enc, f = model.gather_inputs(feats, query)
                with timer.stage("mlp"):
                    pred = model.mlp(enc, f)
                tgt = target[torch.as_tensor(g)].reshape(len(g), H * W, 3)[batch.image_index, batch.pixels]
                loss = loss + (pred - tgt).abs().mean() * len(g) / K
            with timer.stage("backward"):
                opt.zero_grad()
                loss.backward()
            with timer.stage("optimizer"):
                opt.step()

    return step


def _train_timing(model, sample, rounds: int) -> dict[str, tuple[float, dict]]:
    """Best step time and its stage times of the shared and per-camera U-Net variants, interleaved
    (shared, per camera, shared, ...) so that both see the same load; the first round warms up."""
    from deliffas.engine.timing import StageTimer

    opt = torch.optim.Adam(model.parameters(), lr=2e-4)
    steps = {"shared": _train_step(model, opt, sample, True), "per_camera": _train_step(model, opt, sample, False)}
    best = {name: (float("inf"), {}) for name in steps}
    for i in range(rounds):
        for name, step in steps.items():
            timer = StageTimer(torch.device("cpu"))
            t0 = time.perf_counter()
            step(timer)
            wall = time.perf_counter() - t0
            if i and wall < best[name][0]:
                best[name] = (wall, dict(timer.total_ms))
    return best


def run() -> list[Result]:
    from deliffas.io.cameras import Camera  # noqa: F401

    subject, shards, _ = bench_capture()
    sample, info = _sample(shards)
    model = optimize_for_inference(_model(info).eval())  # as evaluate/render (load_run) run it
    rows = []
    with torch.no_grad():
        side = sample.cameras[0].width
        rows += _end_to_end(model, sample, info, sample.cameras[0], f"{side}^2")
        width, height = sized((1285, 940), (96, 64))
        rows += _end_to_end(model, sample, info, sample.cameras[0].rescaled(width, height), f"{height}x{width}")
    rows += _frame_memory(shards, sized(16384, 1024))
    model.train()
    with torch_threads():  # as the stage benchmarks: 2-thread waits under load would decide the ratio
        timing = _train_timing(model, sample, sized(5, 2))
    (shared_t, stages), (per_cam_t, _) = timing["shared"], timing["per_camera"]
    rays = sum(r.num_rays for r in sample.rays)
    rows.append(Result("train", f"small preset two_surface, {side}^2, K={sample.num_cameras} cameras ({rays} rays)",
                       1 / shared_t, "it/s",
                       note="share: " + ", ".join(f"{k} {100 * v / stages['total']:.0f}%" for k, v in stages.items()
                                                  if k != "total")
                       + f" (ray casting runs in the DataLoader workers); {BENCH_THREADS} torch thread"))
    rows.append(Result("train", "U-Net features reused across the K cameras of a frame", per_cam_t / shared_t, "x",
                       baseline="U-Nets once per camera", ratio=per_cam_t / shared_t,
                       note=f"{per_cam_t * 1000:.0f} ms -> {shared_t * 1000:.0f} ms per step"))
    return rows
