"""What every recipe shares: arguments, the default synthetic capture, train + evaluate, outputs.

A recipe parses its arguments with ``recipe_parser``, gets shards with ``prepare_shards`` (from a
subject folder, existing shards, or a synthetic capture it makes itself), runs ``train_and_eval``
per configuration and writes ``results.json``, ``results.md`` and its charts with ``write_outputs``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

logger = logging.getLogger(__name__)

__all__ = ["RecipeSizes", "recipe_parser", "sizes_from_args", "prepare_capture", "prepare_shards",
           "train_and_eval", "write_outputs"]


@dataclass(frozen=True)
class RecipeSizes:
    """Sizes of a recipe run: ``quick`` (minutes on 2 CPU cores, used by tests) or full."""

    frames: int = 40
    test_frames: int = 12
    cameras: int = 12
    size: int = 128
    atlas_res: int = 128
    iters: int = 1500
    cameras_per_frame: int = 3
    preset: str = "small"
    eval_frames: int | None = None

    @staticmethod
    def quick() -> "RecipeSizes":
        return RecipeSizes(frames=6, test_frames=2, cameras=4, size=48, atlas_res=32, iters=8, cameras_per_frame=2,
                           preset="tiny", eval_frames=2)


def recipe_parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--out", type=Path, required=True, help="output folder (results.json, results.md, charts)")
    p.add_argument("--subject", type=Path, default=None, help="DynaCap subject folder (default: a synthetic capture)")
    p.add_argument("--shards", type=Path, default=None, help="already converted shards (skips conversion)")
    p.add_argument("--quick", action="store_true", help="minutes on a CPU; numbers only show the pipeline works")
    p.add_argument("--iters", type=int, default=None, help="training iterations per model")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    return p


def sizes_from_args(args: argparse.Namespace) -> RecipeSizes:
    sizes = RecipeSizes.quick() if args.quick else RecipeSizes()
    if args.iters:
        sizes = dataclasses.replace(sizes, iters=args.iters)
    return sizes


def prepare_capture(out: Path, sizes: RecipeSizes, seed: int = 0, subject: Path | None = None, **synth) -> Path:
    """The subject folder: ``subject`` if given, else a synthetic capture in ``out/subject`` (made once)."""
    if subject is not None:
        return Path(subject)
    from deliffas.data.synth import SynthConfig, synthesize_capture

    path = out / "subject"
    if not (path / "synth.json").is_file():
        synthesize_capture(path, SynthConfig(num_frames=sizes.frames, num_test_frames=sizes.test_frames,
                                             num_cameras=sizes.cameras, width=sizes.size, height=sizes.size,
                                             test_cameras=max(1, sizes.cameras // 4), seed=seed, jobs=2, **synth))
    return path


def prepare_shards(out: Path, subject: Path, sizes: RecipeSizes, name: str = "shards", template: str | None = None,
                   offset_mm: float = 30.0, cameras: Sequence[int] | None = None) -> Path:
    """Convert ``subject`` (optionally with a template variant or another offset) into ``out/<name>``."""
    from deliffas.data.convert import ConvertConfig, convert

    shards = out / name
    convert(subject, shards, ConvertConfig(atlas_res=sizes.atlas_res, jobs=2, resume=True, template=template,
                                           offset_mm=offset_mm, cameras=tuple(cameras) if cameras else None,
                                           progress=False))
    return shards


def train_and_eval(name: str, shards: Path, run_dir: Path, sizes: RecipeSizes, model: str, seed: int = 0,
                   device: str = "cpu", split: str = "novel_view", model_overrides: dict | None = None,
                   **train_kw) -> dict:
    """Train one configuration and evaluate it; returns the evaluation dict plus ``name`` and timings."""
    from deliffas.engine.evaluate import EvalConfig, evaluate
    from deliffas.engine.train import TrainConfig, train

    t0 = time.time()
    cfg = TrainConfig(shards=str(shards), out=str(run_dir), model=model, preset=train_kw.pop("preset", sizes.preset),
                      iters=sizes.iters, cameras_per_frame=sizes.cameras_per_frame, protocol="all", seed=seed,
                      device=device, num_workers=1, checkpoint_every=max(sizes.iters, 1),
                      preview_every=max(sizes.iters, 1), progress=False, model_overrides=model_overrides or {},
                      **train_kw)
    result = train(cfg, resume=True)
    row = evaluate(EvalConfig(run=str(run_dir), split=split, max_frames=sizes.eval_frames, device=device))
    row.update(name=name, train_s=time.time() - t0, train_iters_per_s=result.iters_per_second,
               train_last_loss=result.last_loss)
    print(f"  {name}: PSNR {row['psnr']:.2f} dB, SSIM {row['ssim']:.4f}, "
          f"{sum(row['stage_ms'].values()):.1f} ms/frame", flush=True)
    return row


def write_outputs(out: Path, title: str, rows: list[dict], extra: dict | None = None, notes: Sequence[str] = (),
                  chart: bool = True) -> dict:
    """``results.json``, ``results.md`` (title, table, notes) and a speed-vs-accuracy chart."""
    from deliffas.engine.report import results_table, speed_accuracy_chart

    out.mkdir(parents=True, exist_ok=True)
    payload = {"title": title, "results": rows, **(extra or {}), "command": " ".join(sys.argv)}
    (out / "results.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    md = [f"# {title}", "", results_table(rows), *notes, ""]
    if chart and rows:
        speed_accuracy_chart(rows, out / "speed_accuracy.png", title)
        md += ["![speed vs accuracy](speed_accuracy.png)", ""]
    (out / "results.md").write_text("\n".join(md))
    print("\n".join(md))
    return payload
