"""Measure the web player against ``deliffas render`` (docs/web.md): agreement, size, time to first frame, fps.

    python scripts/web_measure.py OUT_DIR [--size 256] [--atlas 128] [--iters 30] [--screenshot PNG]
                                          [--backend auto|webgl2|cpu] [--models MODEL:PRESET ...]

Makes a synthetic capture (4 cameras of SIZE x SIZE, atlas ATLAS), trains the default model at the ``small``
and ``realtime`` presets and ``two_surface`` at ``small`` for ITERS iterations each (agreement does not need a
good avatar), exports each with ``deliffas export --web``, serves it and opens it in headless Chromium (software
WebGL2), and prints one markdown row per model: PSNR on the person's pixels of 3 frames x 2 cameras against
``deliffas render`` (the minimum and the mean), the folder's size, the time to the first frame, frames per
second from a capture camera and the per-stage split of one frame. ``--backend`` opens the page with
``?backend=`` (the player's WebGL2 or CPU backend; auto: WebGL2 where the browser has it), ``--models`` measures
only those. Needs Chromium and playwright (the dev extra); the browser helpers are ``tests/web/web_page.py``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "web"))
from web_page import page_frame, person_psnr, reference_frames, served_page  # noqa: E402

from deliffas.data.convert import ConvertConfig, convert  # noqa: E402
from deliffas.data.synth import SynthConfig, synthesize_capture  # noqa: E402
from deliffas.engine.export_config import ExportConfig  # noqa: E402
from deliffas.engine.train import TrainConfig, train  # noqa: E402
from deliffas.engine.web import export_web  # noqa: E402
from deliffas.models.model_table import DEFAULT_MODEL  # noqa: E402

MODELS = ((DEFAULT_MODEL, "small"), (DEFAULT_MODEL, "realtime"), ("two_surface", "small"))
CAMERAS, FRAMES = (0, 3), 3


def measure(run: Path, motion: Path, out: Path, screenshot: Path | None = None, backend: str = "auto") -> str:
    for old in out.glob("ref*"):
        shutil.rmtree(old)
    page_dir = export_web(ExportConfig(run=run, out=out / "page", web=True, motion=motion, overwrite=True))
    size = sum(p.stat().st_size for p in page_dir.rglob("*") if p.is_file()) / 1e6
    refs = {c: reference_frames(run, motion, c, FRAMES, out / f"ref{c}") for c in CAMERAS}
    with served_page(page_dir, out, query=f"?backend={backend}") as page:
        name = page.evaluate("() => window.deliffasPlayer.stats().backend")
        first = page.evaluate("() => window.deliffasPlayer.firstFrameMs()")
        scores = [person_psnr(page_frame(page, f, c), refs[c][f]) for c in CAMERAS for f in range(FRAMES)]
        fps = page.evaluate("() => window.deliffasPlayer.benchmark(20, 0)")["fps"]
        stages = page.evaluate("() => window.deliffasPlayer.benchmark(10, 0, true)")["stages_ms"]
        if screenshot is not None:
            page.select_option("#camera", "orbit")
            page.locator("#frame").fill("1")
            page.screenshot(path=str(screenshot))
    split = ", ".join(f"{k} {v:.1f}" for k, v in stages.items())
    return f"{name} | {min(scores):.1f} / {np.mean(scores):.1f} | {size:.2f} | {first:.0f} | {fps:.1f} | {split} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--atlas", type=int, default=128)
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--screenshot", type=Path, help="a PNG of the first model's page")
    ap.add_argument("--backend", choices=("auto", "webgl2", "cpu"), default="auto", help="the player's backend")
    ap.add_argument("--models", nargs="+", metavar="MODEL:PRESET", help="only these (default: all three)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    subject, shards = args.out / "subject", args.out / "shards"
    if not shards.exists():
        synthesize_capture(subject, SynthConfig(num_frames=6, num_test_frames=FRAMES, num_cameras=4, width=args.size,
                                                height=args.size, test_cameras=(3,), seed=0))
        convert(subject, shards, ConvertConfig(atlas_res=args.atlas, progress=False))
    motion = next((subject / "testing").glob("*.motion"))
    models = [tuple(m.split(":")) for m in args.models] if args.models else list(MODELS)
    print("| model | preset | backend | PSNR min / mean (dB) | MB | first frame (ms) | fps | stages (ms) |")
    print("|---|---|---|---|---|---|---|---|")
    for model, preset in models:
        run = args.out / f"run-{model}-{preset}"
        if not run.exists():
            train(TrainConfig(shards=str(shards), out=str(run), model=model, preset=preset, iters=args.iters,
                              cameras_per_frame=2, protocol="all", num_workers=0, checkpoint_every=args.iters,
                              preview_every=0, log_every=10, progress=False))
        shot = args.screenshot if (model, preset) == models[0] else None
        row = measure(run, motion, args.out / f"web-{model}-{preset}", shot, args.backend)
        print(f"| {model} | {preset} | {row}", flush=True)


if __name__ == "__main__":
    main()
