"""The table of docs/performance.md: fps at 256^2, 512^2 and 940x1285 and foreground PSNR of trained runs, one per preset.

Usage (runs trained beforehand, e.g. by ``python -m recipes.presets``)::

    python -m benchmarks.preset_table realtime=RUN small=RUN paper=RUN [--out table.md] [--max-frames N]

For each run: the foreground PSNR on its novel-view split by the plain path and by the fast path (``deliffas eval``
with ``--render-path plain`` and ``fast``), then the fast path's fps on the first test frame's first camera, rescaled to each size:
the pose held (U-Nets cached, the viewer) and with the U-Nets per frame (``deliffas render``), best of 3 on one torch
thread, and a stream of 8 frames with two in flight (``render_stream``). Prints the markdown table and writes it to
``--out``. No targets: machines vary; record the load (``uptime``) beside the numbers.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch

from benchmarks._timing import best_times, torch_threads

SIZES = {"256^2": (256, 256), "512^2": (512, 512), "940x1285": (1285, 940)}


def first_test_frame(run: str) -> tuple:
    """(model, sample, info): the trained run's model (``load_run``) and the first frame of its novel-view split."""
    from deliffas.engine.data_bridge import evaluation_samples
    from deliffas.engine.runs import load_run

    model, record = load_run(run)
    samples, info = evaluation_samples(record["train"]["shards"], "novel_view", max_frames=1, with_rays=False,
                                       protocol="all", temporal_window=model.config.temporal_window)
    return model, next(samples), info


def new_pose_frame(model, sample, info, camera, path):
    """A function that renders ``camera``'s image as a new pose is rendered (``deliffas render``): the U-Nets on the
    frame's normal maps, its surfaces set up, then ``render_camera`` by ``path`` (a ``RenderPathConfig``)."""
    from deliffas.engine.shading import render_camera
    from deliffas.engine.timing import StageTimer
    from deliffas.geometry.raycast import UVRaycaster

    device = torch.device("cpu")

    def frame(*_):
        with torch.no_grad():
            features = model.encode(*sample.normal_maps(device))
            rc = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
            return render_camera(model, features, rc, camera, device, StageTimer(device), render_path=path)
    return frame


def _fps(run: str, max_frames: int | None) -> dict[str, str]:
    from deliffas.engine.shading import render_camera
    from deliffas.fast.frame import render_stream
    from deliffas.fast.config import RenderPathConfig
    from deliffas.engine.timing import StageTimer
    from deliffas.geometry.raycast import UVRaycaster

    model, sample, info = first_test_frame(run)
    device, fast = torch.device("cpu"), RenderPathConfig()
    with torch.no_grad():
        features = model.encode(*sample.normal_maps(device))
    rc = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
    cells = {}
    for size, (w, h) in SIZES.items():
        cam = sample.cameras[0].rescaled(w, h)

        def held(cam=cam):
            with torch.no_grad():
                return render_camera(model, features, rc, cam, device, StageTimer(device), render_path=fast)

        per_frame = new_pose_frame(model, sample, info, cam, fast)

        def stream():
            for _ in render_stream(lambda _i: per_frame(), range(8), 2):
                pass
        with torch_threads(1):
            t = best_times({"held": held, "per_frame": per_frame}, repeat=3, max_rounds=3)
        s = best_times({"stream": stream}, repeat=1, max_rounds=1)["stream"] / 8
        cells[size] = f"{1 / t['held']:.1f} ({1 / t['per_frame']:.1f}; 2 in flight {1 / s:.1f})"
    return cells


def _psnr(run: str, fast: bool, max_frames: int | None) -> float:
    from deliffas.engine.evaluate import EvalConfig, evaluate
    from deliffas.fast.config import RenderPathConfig

    return float(evaluate(EvalConfig(run=run, split="novel_view", max_frames=max_frames,
                                     render_path=RenderPathConfig(path="fast" if fast else "plain"))).foreground.psnr)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="PRESET=RUN_DIR")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--max-frames", type=int, default=None, help="frames of the PSNR evaluation (default: all)")
    args = parser.parse_args(argv)
    lines = ["| preset | " + " | ".join(SIZES) + " | foreground PSNR, plain / fast path |",
             "|---|" + "---|" * len(SIZES) + "---|"]
    runs = [item.partition("=") for item in args.runs]
    for item, (preset, sep, run) in zip(args.runs, runs):
        if not sep or not Path(run).is_dir():
            parser.error(f"{item!r}: expected PRESET=RUN_DIR with an existing run directory")
    _fps(runs[0][2], args.max_frames)  # warm-up, discarded: the row timed first read up to 1.4x slow without it
    for preset, _, run in runs:
        cells = _fps(run, args.max_frames)
        psnr = f"{_psnr(run, False, args.max_frames):.2f} / {_psnr(run, True, args.max_frames):.2f} dB"
        lines.append(f"| {preset} | " + " | ".join(cells[s] for s in SIZES) + f" | {psnr} |")
        print(lines[-1], flush=True)
    load = os.getloadavg()[0]
    table = "\n".join(lines) + (f"\n\nfps with the pose held (in brackets: U-Nets per frame; 2 frames in flight), "
                                f"load average {load:.1f}, {time.strftime('%Y-%m-%d')}\n")
    print(table)
    if args.out:
        args.out.write_text(table)
    return table


if __name__ == "__main__":
    main()
