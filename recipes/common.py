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
from pathlib import Path
from typing import Sequence

from deliffas.engine.run_sizes import RunSizes
from deliffas.engine.train_config import TrainConfig

logger = logging.getLogger(__name__)

__all__ = ["RecipeSizes", "recipe_parser", "sizes_from_args", "prepare_capture", "prepare_shards",
           "train_and_eval", "train_and_eval_seeds", "seed_list", "ablation_sizes", "sized_by_args",
           "FULL_SUPERSAMPLE", "write_outputs", "find_character", "shards_source", "prepare_template_variants",
           "bar_chart"]


RESUMABLE_FIELDS = frozenset({"out", "iters", "checkpoint_every", "preview_every", "log_every", "progress",
                              "num_workers", "device"})
"""TrainConfig fields a recipe may change when it finds its run folder already trained (it continues or
re-evaluates that run); any other change means the folder holds another configuration's run."""
POSE_EVAL_FRAMES = 4
"""Novel-pose frames the ablations evaluate per run (every camera of each: 48 images with 12 cameras)."""
ABLATION_EVAL_FRAMES = 12
"""Novel-view frames the ablations evaluate per run in full mode (36 images with 3 test cameras)."""
ABLATION_ITERS = 1500
"""Training iterations of the ablations in full mode, each on every shaded ray (``RunSizes.rays_per_step``
None): the budget their rows in docs/results.md were measured at, 0.69 dB below an 8 x longer run on the
validation camera (docs/results.md, "Time to quality"); ``--iters`` overrides."""
RECIPE_SCHEDULE = "converge"
"""The learning-rate schedule of every configuration :func:`train_and_eval` trains unless it names its own (the
``paper schedule`` rows): the rows in docs/results.md were measured with it (``deliffas train``'s default is
``hold-decay``, measured in "Time to quality")."""

RecipeSizes = RunSizes
"""The recipes' name for ``deliffas.engine.run_sizes.RunSizes`` (full defaults, ``quick()`` for tests)."""
FULL_SUPERSAMPLE = 3
"""Rays per pixel side of the full recipes' synthetic captures (3 x 3 per pixel): a camera integrates over its
pixels, and one ray per pixel aliases the garment's texture finer than a pixel into ground truth that no
continuous model can reproduce (docs/results.md, "Upper bounds from the capture"). Quick mode renders 1."""


def recipe_parser(description: str, seeds: bool = False) -> argparse.ArgumentParser:
    """The shared options; ``seeds``: also ``--seeds N`` (configurations trained with N seeds, mean ± std)."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--out", type=Path, required=True, help="output folder (results.json, results.md, charts)")
    p.add_argument("--subject", type=Path, default=None, help="DynaCap subject folder (default: a synthetic capture)")
    p.add_argument("--shards", type=Path, default=None, help="already converted shards (skips conversion)")
    p.add_argument("--quick", action="store_true", help="minutes on a CPU; numbers only show the pipeline works")
    p.add_argument("--iters", type=int, default=None, help="training iterations per model")
    p.add_argument("--frames", type=int, default=None, help="training frames of the synthetic capture")
    p.add_argument("--cameras", type=int, default=None,
                   help="cameras of the synthetic capture (a quarter held out as test cameras)")
    p.add_argument("--size", type=int, default=None, help="image side of the synthetic capture, pixels")
    p.add_argument("--supersample", type=int, default=None,
                   help=f"s x s rays per pixel of the synthetic capture (default {FULL_SUPERSAMPLE}; 1 with --quick)")
    p.add_argument("--device", default="cpu", help="cpu | cuda (default cpu)")
    p.add_argument("--seed", type=int, default=0,
                   help="first training seed (seeds are SEED, SEED+1, ...); the capture's seed stays 0")
    if seeds:
        p.add_argument("--seeds", type=int, default=None,
                       help="training seeds per configuration, reported as mean ± std (default 3; 1 with --quick)")
    return p


def sizes_from_args(args: argparse.Namespace) -> RecipeSizes:
    """The run sizes: quick or full defaults, then ``--iters``, ``--frames``, ``--cameras``, ``--size``,
    ``--supersample``."""
    return sized_by_args(RecipeSizes.quick() if args.quick else RecipeSizes(supersample=FULL_SUPERSAMPLE), args)


def sized_by_args(sizes: RecipeSizes, args: argparse.Namespace) -> RecipeSizes:
    """``sizes`` with the fields that ``args`` sets (``--iters``, ``--frames``, ``--cameras``, ``--size``,
    ``--supersample``; each >= 1)."""
    for flag in ("iters", "frames", "cameras", "size", "supersample"):
        value = getattr(args, flag, None)
        if value is not None:
            if value < 1:
                raise SystemExit(f"--{flag} must be >= 1, got {value}")
            sizes = dataclasses.replace(sizes, **{flag: value})
    return sizes


def ablation_sizes(args: argparse.Namespace) -> RecipeSizes:
    """``sizes_from_args`` with the ablations' budget in full mode: ``ABLATION_EVAL_FRAMES`` evaluated frames
    and, unless ``--iters`` is given, ``ABLATION_ITERS`` iterations (three seeds per configuration)."""
    sizes = sizes_from_args(args)
    if args.quick:
        return sizes
    return dataclasses.replace(sizes, eval_frames=sizes.eval_frames or ABLATION_EVAL_FRAMES,
                               iters=args.iters or ABLATION_ITERS)


def seed_list(args: argparse.Namespace) -> list[int]:
    """Training seeds of each configuration: ``--seed`` and the next ``--seeds - 1``."""
    from recipes.seeds import default_seeds

    return [args.seed + i for i in range(default_seeds(args.quick, getattr(args, "seeds", None)))]


def prepare_capture(out: Path, sizes: RecipeSizes, seed: int = 0, subject: Path | None = None, jobs: int = 2,
                    **synth) -> Path:
    """The subject folder: ``subject`` if given, else a synthetic capture in ``out/subject`` (made once, with
    ``sizes.supersample`` rays per pixel side; one made earlier with other sizes is refused).

    ``jobs``: synthesis worker processes (1 = in this process; spawning costs seconds per worker).
    """
    if subject is not None:
        return Path(subject)
    from deliffas.data.synth import SynthConfig, synthesize_capture

    path = out / "subject"
    config = SynthConfig(num_frames=sizes.frames, num_test_frames=sizes.test_frames, num_cameras=sizes.cameras,
                         width=sizes.size, height=sizes.size, test_cameras=max(1, sizes.cameras // 4), seed=seed,
                         jobs=jobs, **{"supersample": sizes.supersample, **synth})
    if (path / "synth.json").is_file():
        _check_same_capture(path, config)
    else:
        synthesize_capture(path, config)
    return path


def _check_same_capture(path: Path, config) -> None:
    """Refuse ``path`` (a finished synthetic capture) when it was rendered with other sizes than ``config``."""
    made = {"supersample": 1, **json.loads((path / "synth.json").read_text()).get("config", {})}  # older: no key
    wanted = {k: getattr(config, k) for k in ("num_frames", "num_cameras", "width", "height", "supersample")}
    diff = _differences(made, wanted)
    if diff:
        raise SystemExit(f"error: {path} holds a capture made with other sizes ({diff}); choose another --out or "
                         "remove that folder")


def _differences(recorded: dict, wanted: dict) -> str:
    """``key: recorded there, wanted now`` for every key of ``wanted`` whose recorded value differs, sorted by key
    and joined with "; " (empty when none differs)."""
    return "; ".join(f"{k}: {recorded.get(k)!r} there, {v!r} now" for k, v in sorted(wanted.items())
                     if recorded.get(k) != v)


def prepare_shards(out: Path, subject: Path, sizes: RecipeSizes, name: str = "shards", template: str | None = None,
                   offset_mm: float = 30.0, cameras: Sequence[int] | None = None, jobs: int = 2,
                   motions: Sequence[str] = (), check: bool = True) -> Path:
    """Convert ``subject`` (optionally with a template variant or another offset, or another template's
    per-frame ``motions`` ``SEQ=FILE``) into ``out/<name>``.

    ``jobs``: conversion worker processes; 1 converts in this process, which is much faster for the
    quick sizes (0.4 s against ~10 s for spawning two workers that import torch).
    """
    from deliffas.data.convert import ConvertConfig, convert

    shards = out / name
    convert(subject, shards, ConvertConfig(atlas_res=sizes.atlas_res, jobs=jobs, resume=True, template=template,
                                           offset_mm=offset_mm, cameras=tuple(cameras) if cameras else None,
                                           motions=tuple(motions), check=check, progress=False))
    return shards


def find_character(subject: Path) -> Path:
    """The subject's ``character/<name>.character`` (or ``SUBJECT/<name>.character``), as ``convert`` finds it."""
    from deliffas.data.subjects import find_character as find

    return find(Path(subject), None)[0]


def shards_source(shards: Path) -> dict:
    """How existing shards were converted: their manifest's ``config`` (``subject``, ``character``,
    ``template``, ``atlas_res``, ``offset_mm``, ``cameras``, ...), to convert the same images again."""
    manifest = Path(shards) / "manifest.json"
    if not manifest.is_file():
        raise FileNotFoundError(f"{shards}: no manifest.json (not a deliffas shard directory)")
    return dict(json.loads(manifest.read_text()).get("config", {}))


def prepare_template_variants(out: Path, character: Path, smooth_iters: int | None = None,
                              coarse_faces: int | None = None, offset_mm: float = 30.0,
                              packing_res: int = 512) -> dict[str, Path]:
    """Template variants of ``character`` (``build_templates``) in ``out``, built once; {variant: folder}.

    ``original`` is always there; ``smooth`` with ``smooth_iters``, ``coarse`` with ``coarse_faces``.
    Pass a folder as ``prepare_shards(..., template=str(folder))``. The report (vertex/face counts,
    shells, atlas statistics) is ``out/report.json``; ``packing_res`` is xatlas' packing resolution.
    """
    from deliffas.data.template_build import TemplateConfig, build_templates

    report_path = Path(out) / "report.json"
    want = {"original"} | ({"smooth"} if smooth_iters is not None else set()) | (
        {"coarse"} if coarse_faces is not None else set())
    stamp = {"character": str(character), "smooth_iters": smooth_iters, "coarse_faces": coarse_faces,
             "offset_mm": float(offset_mm), "packing_res": int(packing_res)}
    stamp_path = Path(out) / "recipe_request.json"
    if not (report_path.is_file() and stamp_path.is_file() and json.loads(stamp_path.read_text()) == stamp):
        build_templates(TemplateConfig(character, out, smooth_iters=smooth_iters, coarse_faces=coarse_faces,
                                       offset_mm=offset_mm, atlas_res=packing_res))
        stamp_path.write_text(json.dumps(stamp, indent=2) + "\n")
    report = json.loads(report_path.read_text())
    missing = want - set(report["variants"])
    if missing:
        raise RuntimeError(f"{report_path}: variants {sorted(missing)} were not built")
    return {name: Path(out) / name for name in sorted(want, key=("original", "smooth", "coarse").index)}


def check_same_configuration(run_dir: Path, cfg) -> None:
    """Refuse a run folder trained with other settings than ``cfg`` (``SystemExit`` naming the fields).

    Recipes resume their runs, so a rerun into the same ``--out`` with another option (dropout, the
    view-direction encoding, the perceptual mode, ...) would otherwise re-evaluate the old model
    and report its numbers under the new option's name.
    """
    path = Path(run_dir) / "train_config.json"
    if not path.is_file():
        return
    recorded = json.loads(path.read_text()).get("train", {})
    wanted = json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
    diff = _differences(recorded, {k: v for k, v in wanted.items() if k not in RESUMABLE_FIELDS})
    if diff:
        raise SystemExit(f"error: {path.parent} holds a run trained with other settings ({diff}); choose another --out "
                         "or remove that folder")


def train_and_eval(name: str, shards: Path, run_dir: Path, sizes: RecipeSizes, model: str, seed: int = 0,
                   device: str = "cpu", split: str = "novel_view", model_overrides: dict | None = None,
                   extra_splits: bool = False, **train_kw) -> dict:
    """Train one configuration and evaluate it; returns the evaluation (``EvalResult.to_json()``) plus ``name``
    and timings.

    ``extra_splits``: also write comparison grids (``run_dir/grid_<split>.png``) and evaluate the novel
    poses (``novel_pose``) and the training cameras (``train_fit``: how well it fits what it saw)."""
    from deliffas.engine.evaluate import EvalConfig, evaluate
    from deliffas.engine.train import train

    t0 = time.time()
    train_kw.setdefault("schedule", RECIPE_SCHEDULE)
    cfg = TrainConfig(shards=str(shards), out=str(run_dir), model=model, preset=train_kw.pop("preset", sizes.preset),
                      iters=sizes.iters, cameras_per_frame=sizes.cameras_per_frame,
                      rays_per_step=train_kw.pop("rays_per_step", sizes.rays_per_step), protocol="all", seed=seed,
                      device=device, num_workers=1, checkpoint_every=max(sizes.iters, 1),
                      preview_every=max(sizes.iters, 1), progress=False, model_overrides=model_overrides or {},
                      **train_kw)
    check_same_configuration(run_dir, cfg)
    result = train(cfg, resume=True)
    row = evaluate(EvalConfig(run=str(run_dir), split=split, max_frames=sizes.eval_frames, device=device,
                              grid=str(Path(run_dir) / f"grid_{split}.png") if extra_splits else None)).to_json()
    row.update(name=name, train_s=time.time() - t0, train_iters_per_s=result.iters_per_second,
               train_last_loss=result.last_loss)
    if extra_splits:
        row["novel_pose"] = evaluate(EvalConfig(run=str(run_dir), split="novel_pose",
                                                max_frames=min(sizes.eval_frames or POSE_EVAL_FRAMES, POSE_EVAL_FRAMES),
                                                device=device, grid=str(Path(run_dir) / "grid_novel_pose.png"))).to_json()
        row["train_fit"] = evaluate(EvalConfig(run=str(run_dir), split="train", max_frames=min(3, sizes.eval_frames or 3),
                                               device=device)).to_json()
    fg = row["foreground"]
    print(f"  {name} (seed {seed}): fg PSNR {fg['psnr']:.2f} dB, fg SSIM {fg['ssim']:.4f}, fg FLIP "
          f"{fg['flip'] if fg['flip'] is None else format(fg['flip'], '.4f')} (official PSNR {row['psnr']:.2f} dB), "
          f"{sum(row['stage_ms'].values()):.1f} ms/frame", flush=True)
    return row


def train_and_eval_seeds(name: str, shards: Path, run_dir: Path, sizes: RecipeSizes, model: str, seeds: Sequence[int],
                         device: str = "cpu", extra_splits: bool = True, **kw) -> dict:
    """``train_and_eval`` once per training seed (``run_dir/seed<S>``, with grids, novel poses and the fit
    unless ``extra_splits`` is False: then the novel views only); the row is the first seed's evaluation plus
    ``seeds``, ``per_seed`` and ``stats`` (mean ± std, ``recipes.seeds``)."""
    from recipes.seeds import train_seeds

    def one(seed: int, run: Path):
        row = train_and_eval(name, shards, run, sizes, model, seed, device, extra_splits=extra_splits, **kw)
        return row, row.pop("novel_pose", None), row.pop("train_fit", None)

    return train_seeds(name, seeds, run_dir, one)


def write_outputs(out: Path, title: str, rows: list[dict], extra: dict | None = None, notes: Sequence[str] = (),
                  chart: bool = True) -> dict:
    """``results.json``, ``results.md`` (title, the mean ± std table when rows have seeds, the first seed's
    full table, notes) and a speed-vs-accuracy chart."""
    from deliffas.engine.report import results_table, speed_accuracy_chart
    from recipes.seeds import stats_table

    out.mkdir(parents=True, exist_ok=True)
    payload = {"title": title, "results": rows, **(extra or {}), "command": " ".join(sys.argv)}
    (out / "results.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    md = [f"# {title}", ""]
    if rows and all("stats" in r for r in rows):
        md += ["## Mean ± std over training seeds (foreground metrics: the headline)", "", *stats_table(rows), "",
               "## First seed, every metric", ""]
    md += [results_table(rows), *notes, ""]
    if chart and rows:
        speed_accuracy_chart(rows, out / "speed_accuracy.png", title)
        md += ["![speed vs accuracy](speed_accuracy.png)", ""]
    (out / "results.md").write_text("\n".join(md))
    print("\n".join(md))
    return payload


def bar_chart(rows: Sequence[dict], path: Path, title: str, key: str = "psnr", ylabel: str = "PSNR (dB), held-out cameras",
              groups: Sequence[str] | None = None) -> Path:
    """One bar per row of ``row[key]`` (rows whose value is None are drawn empty and labelled n/a).

    ``groups`` (one label per row, optional) colours the bars by group, e.g. the template variant.
    """
    from deliffas.engine.report import pyplot, save_figure

    plt = pyplot()

    values = [r.get(key) for r in rows]
    names = [str(r.get("name", r.get("model"))) for r in rows]
    palette = plt.get_cmap("tab10")
    group_ids = {g: i for i, g in enumerate(dict.fromkeys(groups))} if groups else {}
    colors = [palette(group_ids[g] % 10) for g in groups] if groups else ["tab:blue"] * len(rows)
    fig, ax = plt.subplots(figsize=(max(4.8, 1.1 * len(rows) + 1.5), 4.4), dpi=120)
    finite = [v for v in values if v is not None]
    bars = ax.bar(range(len(rows)), [v if v is not None else 0.0 for v in values], color=colors, zorder=3)
    for b, v in zip(bars, values):
        ax.annotate("n/a" if v is None else f"{v:.3g}", (b.get_x() + b.get_width() / 2, b.get_height()),
                    textcoords="offset points", xytext=(0, 3), ha="center", fontsize=7)
    if finite:
        lo, hi = min(finite), max(finite)
        pad = max(hi - lo, 1e-6 * max(abs(hi), 1.0))
        ax.set_ylim(max(0.0, lo - 2 * pad) if lo >= 0 else lo - 2 * pad, hi + pad)
    ax.set_xticks(range(len(rows)), names, rotation=25, ha="right", fontsize=7)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(axis="y", alpha=0.3, zorder=0)
    if groups:
        from matplotlib.patches import Patch

        ax.legend(handles=[Patch(color=palette(i % 10), label=g) for g, i in group_ids.items()], fontsize=7)
    return save_figure(fig, path)
