"""The viewer's frame rate at 512^2 (small preset) against the engine's renderer alone.

The viewer renders as ``deliffas view`` serves it: through the CPU fast path (``ViewConfig.render_path``'s
default), and
``render_frame`` / ``render_camera`` are given the same path; the plain viewer's rate is a row without target.
Smoke mode: 64^2, 2 views, one timed pass."""

from __future__ import annotations

import dataclasses
import json
import tempfile
import threading
import time
from pathlib import Path

import torch

from benchmarks._capture import bench_capture
from benchmarks.bench_engine import _model, _sample
from benchmarks.common import Result, sized

SIDE, VIEWS = 512, 8


def _run_dir(model, shards) -> Path:
    """A run directory holding ``model`` (untrained weights time the same) on ``shards``."""
    from deliffas.models.checkpoint import save_checkpoint

    run = Path(tempfile.mkdtemp(prefix="deliffas-bench-view-")) / "run"
    save_checkpoint(run / "checkpoint", model)
    (run / "train_config.json").write_text(json.dumps({"train": {"shards": str(shards)}}))
    return run


def _orbit(sample, side: int, views: int) -> list:
    from deliffas.engine.render import orbit_cameras

    centre = sample.inner_verts.mean(0)
    ref = sample.cameras[0]
    radius = float(((ref.center - centre)[[0, 2]] ** 2).sum() ** 0.5)
    return orbit_cameras(ref, [centre] * views, radius, float(ref.center[1]), (side, side))


def run() -> list[Result]:
    import cv2

    from deliffas.engine.runs import load_run
    from deliffas.engine.shading import render_camera, render_frame
    from deliffas.fast.frame import path_for_device
    from deliffas.engine.view_config import ViewConfig
    from deliffas.engine.timing import StageTimer
    from deliffas.engine.view.renderer import RenderWorker, ViewRenderer, ViewRequest
    from deliffas.engine.view.scene import ViewScene
    from deliffas.geometry.raycast import UVRaycaster

    _, shards, _ = bench_capture()
    sample, info = _sample(shards, K=1)
    run_dir = _run_dir(_model(info), shards)
    model, _ = load_run(run_dir)
    side, views = sized((SIDE, VIEWS), (64, 2))
    tries = sized(2, 1)
    cams = _orbit(sample, side, views)
    device = torch.device("cpu")
    rc = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
    fast = path_for_device(ViewConfig.render_path, device)

    def direct(with_cnn: bool) -> float:
        features = model.encode(*sample.normal_maps(device))
        t0 = time.perf_counter()
        for cam in cams:
            if with_cnn:
                render_frame(model, dataclasses.replace(sample, cameras=[cam]), rc, device, StageTimer(),
                             render_path=fast)
            else:
                render_camera(model, features, rc, cam, device, StageTimer(), render_path=fast)
        return (time.perf_counter() - t0) / len(cams)

    scene = ViewScene([str(run_dir)])
    done = threading.Semaphore(0)

    def encode(result) -> None:  # what the server does with each result before sending it
        cv2.imencode(".png", result.image)
        done.release()

    frame = scene.frame_labels.index(sample.frame) if sample.frame in scene.frame_labels else 0

    def viewer(worker) -> float:
        t0 = time.perf_counter()
        for i, cam in enumerate(cams):
            worker.submit(ViewRequest(cam, frame, "rgb", canvas=(side, side), serial=i))
            done.acquire()
        return (time.perf_counter() - t0) / len(cams)

    worker = RenderWorker(ViewRenderer(scene, render_path=fast), encode)
    plain_worker = RenderWorker(ViewRenderer(scene), encode)
    try:
        with torch.no_grad():
            direct(True), viewer(worker), viewer(plain_worker)  # warm-up: open3d, kernels, the frame's features
            alone = min(direct(True) for _ in range(tries))
            cached = min(direct(False) for _ in range(tries))
            served = min(viewer(worker) for _ in range(tries))
            plain = min(viewer(plain_worker) for _ in range(tries))
    finally:
        worker.stop()
        plain_worker.stop()
    fps = 1.0 / served
    path = "fast path" if fast.fast else "plain path"
    return [
        Result("view", f"viewer {side}^2 small two_surface, camera orbit (frame fixed): fps", fps, "fps",
               target=">= 10", passed=fps >= 10, note=f"{served * 1000:.1f} ms per image incl. PNG encoding; {path}"),
        Result("view", f"viewer {side}^2, plain path (--render-path plain): fps", 1.0 / plain, "fps",
               ratio=plain / served,
               baseline="the viewer as served", note=f"{plain * 1000:.1f} ms per image; no target"),
        Result("view", f"viewer {side}^2: time per image / render_frame alone", served / alone, "ratio",
               baseline=f"render_frame {alone * 1000:.1f} ms (U-Net every call)", ratio=served / alone,
               target="<= 1.2", passed=served / alone <= 1.2),
        Result("view", f"viewer {side}^2: time per image / render_camera, features cached", served / cached, "ratio",
               baseline=f"render_camera {cached * 1000:.1f} ms", ratio=served / cached,
               note="the viewer's own overhead: worker thread, panel composition, PNG encoding"),
    ]
