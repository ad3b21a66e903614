"""The device check (``scripts/device_check.sh``): train, evaluate and render on one device, with its numbers.

Self-contained for a bare GPU box that has torch, numpy, scipy, h5py, safetensors, opencv, matplotlib and tqdm
and none of open3d, pymeshlab, xatlas, pycolmap, trimesh, viser or av: the uv maps come from the torch
rasteriser (``uv="torch"``) or the C one (where a C compiler builds it), the capture is a small shard set made
beforehand by ``--prepare`` (which needs the whole stack) and carried there with the repository.

Printed (and written as JSON with ``--json``), per case (``--model``, by default the trainer's default model, at a
zoo preset and an image size):

* ``train``: it/s of ``train_step`` on in-memory samples of the shards' frames at the case's size and atlas
  side (images resized, cameras rescaled, normal maps rebuilt at the preset's side), uvs rasterised every
  step on the device as the trainer does (shard reading by the DataLoader is not in it), and the ms of the
  step's uv stage;
* ``render``: frames rendered one by one with the U-Nets run per frame (a new pose every frame) and the torch
  rasteriser's uvs: fps over the wall clock, and the ms per stage (uv, cnn, sample, mlp) from a second,
  synchronised pass; ``render_default_uv``: the same with ``uv="auto"`` (the C rasteriser where it builds);
* ``agreement``: PSNR between one frame rendered on the device (torch rasteriser) and on the CPU with the
  same weights from the C/numpy rasteriser's rays (on ``--device cpu``: the two rasterisers);

and once: ``trainer`` (``deliffas.engine.train.train`` on the shards with the torch uv source: it/s),
``trainer_default_uv`` (the same with ``uv="auto"``: the C rasteriser in the data workers where it builds) and
``eval`` (``evaluate`` of the first run with the torch uv source: per-stage ms, fps, PSNR) and
``eval_default_uv`` (``evaluate`` of the second run with ``uv="auto"``).

Usage::

    python -m benchmarks.device_check --prepare DATA         # on a full install: synth + convert
    python -m benchmarks.device_check --data DATA --device cuda [--quick] [--json OUT]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

__all__ = ["Case", "FULL", "QUICK", "prepare", "default_model", "run_checks", "main"]

PSNR_MIN = 50.0
"""Device-vs-CPU agreement of one rendered frame (dB) the check requires."""


@dataclass(frozen=True)
class Case:
    """One measured configuration: a zoo preset at an image size."""

    preset: str
    width: int
    height: int
    iters: int
    render_frames: int


FULL = (Case("paper", 940, 1285, 300, 60), Case("small", 256, 256, 300, 120))
"""On a GPU: the paper preset at the paper's image size, the small preset at 256²."""
QUICK = (Case("tiny", 48, 48, 3, 2), Case("small", 64, 64, 2, 2))
"""On the CPU (tests): the same steps at tiny sizes."""


def prepare(data: Path, frames: int = 8, cameras: int = 4, size: int = 96, atlas_res: int = 128) -> Path:
    """Synthesise a small capture and convert it to ``data/shards`` (needs the whole install); also copy the
    pure-Python ``jaxtyping`` and ``wadler_lindig`` packages to ``data/vendor`` for a box without them."""
    import shutil

    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture

    data.mkdir(parents=True, exist_ok=True)
    if not (data / "subject" / "synth.json").is_file():
        synthesize_capture(data / "subject", SynthConfig(num_frames=frames, num_test_frames=2, num_cameras=cameras,
                                                         width=size, height=size, test_cameras=(cameras - 1,), seed=0))
    if not (data / "shards").is_dir():
        convert(data / "subject", data / "shards", ConvertConfig(atlas_res=atlas_res, progress=False))
    for name in ("jaxtyping", "wadler_lindig"):
        module = __import__(name)
        target = data / "vendor" / name
        if not target.is_dir():
            shutil.copytree(Path(module.__file__).parent, target, ignore=shutil.ignore_patterns("__pycache__"))
    return data / "shards"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float((a.float().cpu() - b.float().cpu()).square().mean())
    return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")


def default_model() -> str:
    """The model ``deliffas train`` trains when none is named (``TrainConfig.model``)."""
    from deliffas.engine.train_config import TrainConfig

    return TrainConfig.model


def _case_data(shards: str, case: Case, device: torch.device, model_name: str) -> tuple:
    """The case's model (fresh weights on ``device``), its in-memory samples (every training frame, all
    training cameras, at the case's size) and the shards' info."""
    import cv2

    from deliffas.engine.data_bridge import evaluation_samples, shard_info
    from deliffas.engine.train_config import TrainConfig, resolve_model_config
    from deliffas.geometry.atlas import uv_texel_table
    from deliffas.geometry.frame_geometry import FrameGeometryBuilder
    from deliffas.data.shards import ShardSet
    from deliffas.models.deliffas import DeliffasModel

    cfg = resolve_model_config(TrainConfig(shards=shards, out="unused", model=model_name, preset=case.preset,
                                           device=str(device)))
    info = shard_info(shards)
    meta = ShardSet(shards).meta
    frames = list(evaluation_samples(shards, "train", protocol="all", temporal_window=info["temporal_window"])[0])
    builder = FrameGeometryBuilder(info["faces"], meta.outer_offsets, uv_texel_table(info["atlas"], cfg.atlas_res))
    geometry = builder.build(np.stack([s.inner_verts for s in frames]))
    size = (case.width, case.height)
    resize = lambda a: np.stack([cv2.resize(x, size, interpolation=cv2.INTER_LINEAR) for x in a])  # noqa: E731
    samples = []
    for i, s in enumerate(frames):
        ni, no = geometry.window(i, cfg.temporal_window)
        samples.append(dataclasses.replace(
            s, images=resize(s.images), masks=resize(s.masks), cameras=[c.rescaled(*size) for c in s.cameras],
            normal_inner=ni.numpy(), normal_outer=no.numpy(), inner_verts=geometry.inner[i],
            outer_verts=geometry.outer[i], rays=[]))
    torch.manual_seed(0)
    return DeliffasModel(cfg).to(device), samples, info


def _train(model, samples, info, device: torch.device, iters: int, k: int = 4) -> dict:
    """it/s of ``iters`` training steps (after 3 warm-up steps), the uvs rasterised every step."""
    from deliffas.engine.data_bridge import with_torch_rays
    from deliffas.engine.train_step import train_step

    opt = torch.optim.Adam(model.parameters(), lr=2e-4, betas=(0.9, 0.999), eps=1e-7)
    n_cam = samples[0].num_cameras
    k = min(k, n_cam)
    uv_s = 0.0
    last: dict = {}

    def step(it: int) -> float:
        nonlocal last
        s = samples[it % len(samples)]
        pick = [(it + j) % n_cam for j in range(k)]
        s = dataclasses.replace(s, images=s.images[pick], masks=s.masks[pick], cameras=[s.cameras[j] for j in pick],
                                camera_ids=s.camera_ids[pick])
        t0 = time.perf_counter()
        s = with_torch_rays(s, info["faces"], info["atlas"], device)
        _sync(device)
        t1 = time.perf_counter()
        last = train_step(model, s, opt, device)
        return t1 - t0

    for it in range(3):
        step(it)
    _sync(device)
    t0 = time.perf_counter()
    for it in range(iters):
        uv_s += step(it)
    _sync(device)
    seconds = time.perf_counter() - t0
    return {"iters": iters, "it_per_s": iters / seconds, "uv_ms_per_step": 1000 * uv_s / iters,
            "last_psnr_rays": last.get("psnr_rays")}


@torch.no_grad()
def _render_frame(model, sample, cam, info, device: torch.device, timer, uv: str = "torch") -> torch.Tensor:
    """One (H, W, 3) image of ``sample``'s pose from ``cam``: the U-Nets, then ``render_camera`` with the uvs of
    ``uv``."""
    from deliffas.engine.shading import render_camera
    from deliffas.fast.config import RenderPathConfig
    from deliffas.geometry.raycast import UVRaycaster

    with timer.stage("cnn"):
        features = model.encode(*sample.normal_maps(device))
    raycaster = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
    return render_camera(model, features, raycaster, cam, device, timer,
                         render_path=RenderPathConfig(path="plain", uv=uv))


def _render(model, samples, info, device: torch.device, frames: int, uv: str = "torch") -> dict:
    """Frames with the U-Nets run per frame and the uvs of ``uv``: fps over the wall clock (no per-stage
    synchronisation), then the per-stage ms from a synchronised pass."""
    from deliffas.engine.rays import uv_source
    from deliffas.engine.timing import STAGES, StageTimer

    model.eval()
    cam = samples[0].cameras[-1]
    for i in range(2):  # warm-up
        _render_frame(model, samples[i % len(samples)], cam, info, device, StageTimer("cpu"), uv)
    _sync(device)
    t0 = time.perf_counter()
    for i in range(frames):
        _render_frame(model, samples[i % len(samples)], cam, info, device, StageTimer("cpu"), uv)
    _sync(device)
    fps = frames / (time.perf_counter() - t0)
    timer = StageTimer(device)
    for i in range(frames):
        _render_frame(model, samples[i % len(samples)], cam, info, device, timer, uv)
    return {"frames": frames, "fps": fps, "stage_ms": {s: timer.per_unit(frames)[s] for s in STAGES},
            "uv": uv_source(device, uv, cam.width * cam.height)}


@torch.no_grad()
def _agreement(model, sample, info, device: torch.device) -> dict:
    """PSNR of one frame rendered on ``device`` (torch rasteriser) against the CPU with the same weights and the
    C/numpy rasteriser's rays; on a CPU device this compares the two rasterisers."""
    from deliffas.engine.rays import paint_images, ray_query, stack_rays
    from deliffas.fast.rasterize import rasterized_camera_rays
    from deliffas.engine.timing import StageTimer
    from deliffas.geometry.raycast import UVRaycaster

    model.eval()
    cam = sample.cameras[-1]
    got = _render_frame(model, sample, cam, info, device, StageTimer("cpu"))
    cpu_model = copy.deepcopy(model).cpu()
    features = cpu_model.encode(*sample.normal_maps("cpu"))
    raycaster = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
    batch = stack_rays([rasterized_camera_rays(raycaster, cam)], [0])
    rgb = cpu_model.shade_chunked(features, ray_query(batch, cpu_model.spec))
    ref = paint_images(rgb, batch, 1, cam.height, cam.width)[0]
    psnr = _psnr(got, ref)
    return {"psnr_db": psnr, "min_db": PSNR_MIN, "passed": psnr >= PSNR_MIN, "rays": batch.num_rays,
            "reference": "cpu, C/numpy rasteriser"}


def _trainer_and_eval(shards: str, out: Path, device: torch.device, iters: int, preset: str, model_name: str) -> dict:
    """``train`` on the shards with the torch uv source and with the default one, then ``evaluate`` of the first
    run."""
    from deliffas.engine.evaluate import EvalConfig, evaluate
    from deliffas.engine.rays import uv_source
    from deliffas.engine.train import TrainConfig, train
    from deliffas.fast.config import RenderPathConfig

    got = {}
    for key, uv in (("trainer", "torch"), ("trainer_default_uv", "auto")):
        cfg = TrainConfig(shards=shards, out=f"{out}_{uv}", model=model_name, preset=preset, iters=iters,
                          protocol="all", device=str(device), uv=uv, num_workers=2, checkpoint_every=iters,
                          preview_every=0, progress=False)
        res = train(cfg)
        got[key] = {"preset": preset, "iters": res.iterations, "it_per_s": res.iters_per_second,
                    "stage_ms": res.stage_ms, "uv": uv_source(device, uv)}
    keys = ("stage_ms", "fps", "fps_shared_cnn", "psnr", "images", "resolution", "uv")
    for key, uv in (("eval", "torch"), ("eval_default_uv", "auto")):
        ev = evaluate(EvalConfig(run=f"{out}_{uv}", split="novel_view", device=str(device),
                                 render_path=RenderPathConfig(path="plain", uv=uv)))
        got[key] = {k: ev.to_json()[k] for k in keys}
    return got


def run_checks(shards: str, device: torch.device, cases, trainer_iters: int, trainer_preset: str,
               model_name: str | None = None) -> dict:
    """Every check on ``device`` for the zoo model ``model_name`` (default: :func:`default_model`); the JSON-ready
    record (see the module docstring)."""
    model_name = model_name or default_model()
    out: dict = {"device": str(device), "model": model_name, "torch": torch.__version__,
                 "python": sys.version.split()[0],
                 "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None, "cases": []}
    with tempfile.TemporaryDirectory() as tmp:
        _say(f"trainer + eval ({trainer_preset}, {trainer_iters} iterations, shards as stored)")
        out.update(_trainer_and_eval(shards, Path(tmp) / "run", device, trainer_iters, trainer_preset, model_name))
        _say(json.dumps({k: out[k] for k in ("trainer", "trainer_default_uv", "eval", "eval_default_uv")},
                        default=float))
    for case in cases:
        _say(f"{model_name} {case.preset} at {case.width}x{case.height}")
        model, samples, info = _case_data(shards, case, device, model_name)
        row = {"preset": case.preset, "size": [case.width, case.height], "atlas_res": model.config.atlas_res,
               "parameters": model.num_parameters(), "rays_per_image": None}
        row["train"] = _train(model, samples, info, device, case.iters)
        _say(f"  train  {row['train']['it_per_s']:.2f} it/s (uv {row['train']['uv_ms_per_step']:.2f} ms/step)")
        row["render"] = _render(model, samples, info, device, case.render_frames)
        row["render_default_uv"] = _render(model, samples, info, device, case.render_frames, "auto")
        for key in ("render", "render_default_uv"):
            ms = row[key]["stage_ms"]
            _say(f"  render {row[key]['fps']:.1f} fps, U-Nets per frame, uv {row[key]['uv']}; ms uv {ms['uv']:.2f} "
                 f"cnn {ms['cnn']:.2f} sample {ms['sample']:.2f} mlp {ms['mlp']:.2f}")
        row["agreement"] = _agreement(model, samples[0], info, device)
        row["rays_per_image"] = row["agreement"]["rays"]
        _say(f"  agreement {row['agreement']['psnr_db']:.1f} dB vs {row['agreement']['reference']} "
             f"({'ok' if row['agreement']['passed'] else 'FAILED'}: >= {PSNR_MIN} dB)")
        out["cases"].append(row)
        del model, samples
        if device.type == "cuda":
            torch.cuda.empty_cache()
    out["passed"] = all(c["agreement"]["passed"] for c in out["cases"])
    return out


def _say(text: str) -> None:
    print(f"[device_check] {text}", flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.device_check", description=__doc__.split("\n\n")[0])
    p.add_argument("--prepare", metavar="DATA", help="synthesise and convert the small capture into DATA, then exit")
    p.add_argument("--data", default="device_check_data", help="folder made by --prepare (its shards/)")
    p.add_argument("--device", default="cuda", help="cuda | cuda:N | cpu (default cuda)")
    p.add_argument("--model", default=None, help="zoo model to check (default: deliffas train's default, "
                   f"{default_model()})")
    p.add_argument("--quick", action="store_true", help="tiny sizes and a few iterations (the default on cpu)")
    p.add_argument("--json", help="also write the record to this JSON file")
    args = p.parse_args(argv)
    if args.prepare:
        _say(f"shards at {prepare(Path(args.prepare))}")
        return 0
    shards = Path(args.data) / "shards"
    if not (shards / "manifest.json").is_file():
        print(f"device_check: {shards} holds no shard set; make it with `scripts/device_check.sh --prepare "
              f"{args.data}` on a full install and carry it", file=sys.stderr)
        return 2
    from deliffas.engine.devices import resolve_device
    from deliffas.engine.train_config import TrainConfig

    try:  # the trainer's own check of the model name, before any work
        TrainConfig(shards=str(shards), out="unused", model=args.model or default_model())
    except ValueError as exc:
        print(f"device_check: --model: {exc}", file=sys.stderr)
        return 2

    try:
        device = resolve_device(args.device)
    except ValueError as exc:
        print(f"device_check: --device: {exc}", file=sys.stderr)
        return 2
    quick = args.quick or device.type == "cpu"
    record = run_checks(str(shards), device, QUICK if quick else FULL, trainer_iters=4 if quick else 200,
                        trainer_preset="tiny" if quick else "small", model_name=args.model)
    text = json.dumps(record, indent=2, default=float)
    if args.json:
        Path(args.json).write_text(text + "\n")
    print(text)
    _say("passed" if record["passed"] else "FAILED: a device-vs-CPU agreement is below the bound")
    return 0 if record["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
