"""Time to quality: held-out quality against training wall-clock, the default run against the paper's schedule.

Usage: ``python -m recipes.time_to_quality --out OUT [--quick] [--seeds N] [--iters N] [--budgets S,...]
[--subject DIR | --shards DIR]``.

Each configuration is trained over seeds on the 256 x 256 recipe capture (40 training + 10 test frames,
12 cameras: a quarter held out as test cameras and one training camera as the validation split; rendered with
3 x 3 rays per pixel, ``--supersample`` to change); at
``CHECKPOINTS`` fractions of the run the model is evaluated on the validation camera (foreground and
masked PSNR, FLIP) and on the held-out test cameras. Training seconds exclude the evaluations. Writes
``results.json``, ``results.md`` and ``time_to_quality.png`` (masked PSNR against seconds).

Configurations: ``default`` is ``deliffas train`` without options (``TrainConfig`` defaults:
``two_surface_reflect_texture``, the ``hold-decay`` schedule, at most 8192 rays per iteration);
``two_surface_texture`` the same without the reflected view direction, on every shaded ray; ``paper schedule`` is
the paper's model and schedule (``two_surface``, Adam 2e-4 with the official decay, every shaded ray), the default
before this recipe existed; ``default, S s budget`` is the default trained for S seconds (``deliffas train
--time-budget S``: the iterations that fit on the machine it runs on), evaluated once at its end (``--budgets``,
default :data:`FULL_BUDGETS`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from deliffas.engine.eval_result import EvalResult
from deliffas.engine.run_sizes import RunSizes
from recipes.common import FULL_SUPERSAMPLE, prepare_capture, prepare_shards, recipe_parser, seed_list, sized_by_args

CAPTURE = RunSizes(frames=40, test_frames=10, cameras=12, size=256, atlas_res=256, iters=0, cameras_per_frame=3,
                   preset="small", eval_frames=10, supersample=FULL_SUPERSAMPLE)
"""The recipe capture at 256 px, 3 x 3 rays per pixel (``iters`` 0: the configurations' own)."""
FULL_BUDGETS = (540.0,)
"""Time budgets (seconds) of the default's ``--time-budget`` runs in full mode: 9 minutes, so that the
whole ``deliffas train`` ends within 10."""
QUICK_BUDGETS = (6.0,)
"""Time budgets of ``--quick``: enough for the timed first iterations and a few more."""
CHECKPOINTS = (0.125, 0.25, 0.5, 0.75, 1.0)
"""Fractions of the run at which the model is evaluated."""
CONFIGS: dict[str, dict] = {
    "default": {},
    "two_surface_texture": {"model": "two_surface_texture", "rays_per_step": None},
    "paper schedule": {"model": "two_surface", "schedule": "paper", "rays_per_step": None},
}
"""Name -> TrainConfig fields that differ from ``deliffas train``'s defaults."""


def _scores(ev: EvalResult) -> dict:
    fg = ev.foreground
    return {"fg_psnr": fg.psnr, "masked_psnr": fg.masked_psnr, "fg_flip": fg.flip}


def _split_scores(run_dir: Path, eval_frames: int | None, device: str) -> dict:
    """The run's scores on the validation camera and on the test cameras (``novel_view``)."""
    from deliffas.engine.evaluate import EvalConfig, evaluate

    return {split: _scores(evaluate(EvalConfig(run=str(run_dir), split=split, max_frames=eval_frames, device=device)))
            for split in ("validation", "novel_view")}


def run_curve(shards: Path, run_dir: Path, fields: dict, iters: int, seed: int, eval_frames: int | None,
              device: str = "cpu") -> list[dict]:
    """Train one configuration, evaluating at ``CHECKPOINTS``; one point per checkpoint (seconds, scores).

    A finished run (``curve.json`` in ``run_dir``) is read back instead of retrained."""
    from deliffas.engine.train import TrainConfig, Trainer

    done = run_dir / "curve.json"
    if done.is_file():
        return json.loads(done.read_text())
    cfg = TrainConfig(shards=str(shards), out=str(run_dir), iters=iters, protocol="all", seed=seed, device=device,
                      validation_cameras=1, checkpoint_every=iters,
                      preview_every=0, progress=False, **fields)
    trainer = Trainer(cfg, overwrite=True)
    marks = sorted({max(1, round(f * iters)) for f in CHECKPOINTS})
    points, seconds, it = [], 0.0, 0
    for mark in marks:
        t0 = time.perf_counter()
        for it in range(it, mark):
            trainer.step(it)
        it = mark
        seconds += time.perf_counter() - t0
        trainer.checkpoint(mark)
        point = {"iteration": mark, "train_s": seconds, **_split_scores(run_dir, eval_frames, device)}
        points.append(point)
        print(f"  {run_dir.parent.name} seed {seed}: {mark} it, {seconds:.0f} s, validation masked PSNR "
              f"{point['validation']['masked_psnr']:.2f} dB", flush=True)
    if hasattr(trainer.stream, "close"):
        trainer.stream.close()
    done.write_text(json.dumps(points, indent=1) + "\n")
    return points


def run_budget(shards: Path, run_dir: Path, budget: float, seed: int, eval_frames: int | None,
               device: str = "cpu", fields: dict | None = None) -> list[dict]:
    """Train the default for ``budget`` seconds (``TrainConfig.time_budget``) and evaluate it once: a
    one-point curve (the iterations it planned, its training seconds, the scores). A finished run
    (``curve.json``) is read back."""
    from deliffas.engine.train import TrainConfig, train

    done = run_dir / "curve.json"
    if done.is_file():
        return json.loads(done.read_text())
    cfg = TrainConfig(shards=str(shards), out=str(run_dir), time_budget=budget, protocol="all", seed=seed,
                      device=device, validation_cameras=1, checkpoint_every=10**9, preview_every=0, progress=False,
                      **(fields or {}))
    t0 = time.perf_counter()
    result = train(cfg, overwrite=True)
    point = {"iteration": result.iterations, "train_s": time.perf_counter() - t0, "budget_s": budget,
             **_split_scores(run_dir, eval_frames, device)}
    print(f"  {budget:g} s budget seed {seed}: {result.iterations} it, {point['train_s']:.0f} s, validation masked "
          f"PSNR {point['validation']['masked_psnr']:.2f} dB", flush=True)
    done.write_text(json.dumps([point], indent=1) + "\n")
    return [point]


def curve_chart(curves: dict[str, list[list[dict]]], path: Path, title: str, split: str = "validation") -> Path:
    """Masked PSNR on ``split`` against training seconds: one line per seed, one colour per configuration."""
    from deliffas.engine.report import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    for i, (name, seeds) in enumerate(curves.items()):
        for j, points in enumerate(seeds):
            ax.plot([p["train_s"] / 60 for p in points], [p[split]["masked_psnr"] for p in points], "o-",
                    color=f"C{i}", alpha=0.9 if j == 0 else 0.45, label=name if j == 0 else None)
    ax.set_xlabel("training wall-clock (minutes, evaluations excluded)")
    ax.set_ylabel(f"masked PSNR (dB), {split} camera")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def _budgets(text: str) -> tuple[float, ...]:
    """``--budgets``: comma-separated seconds, or ``none``."""
    from deliffas.options import positive_float

    return () if text.strip() == "none" else tuple(positive_float(t) for t in text.split(","))


def _row(name: str, fields: dict, seeds: list[int], seeds_points: list[list[dict]]) -> dict:
    """One configuration's means over seeds of its last points (iterations, seconds, scores)."""
    finals = [pts[-1] for pts in seeds_points]
    row = {"name": name, "fields": fields, "iters": round(sum(f["iteration"] for f in finals) / len(finals)),
           "seeds": seeds, "curves": seeds_points, "train_s": sum(f["train_s"] for f in finals) / len(finals)}
    for split in ("validation", "novel_view"):
        for key in ("fg_psnr", "masked_psnr", "fg_flip"):
            row[f"{split}_{key}"] = sum(f[split][key] for f in finals) / len(finals)
    return row


def main(argv=None) -> dict:
    from deliffas.engine.train_config import TrainConfig

    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--configs", default=None,
                   help=f"comma-separated configurations to run, of {','.join(CONFIGS)} (default all); finished "
                        "runs in OUT are read back, so runs split over processes join in a last call without it")
    p.add_argument("--budgets", type=_budgets, default=None,
                   help="comma-separated time budgets (seconds) for the default trained with --time-budget, one "
                        f"scored point each, or none (default {','.join(f'{b:g}' for b in FULL_BUDGETS)}; "
                        f"{','.join(f'{b:g}' for b in QUICK_BUDGETS)} with --quick)")
    args = p.parse_args(argv)
    names = [n.strip() for n in args.configs.split(",")] if args.configs else list(CONFIGS)
    if any(n not in CONFIGS for n in names):
        p.error(f"--configs: expected names from {','.join(CONFIGS)}, got {args.configs!r}")
    budgets = args.budgets if args.budgets is not None else (QUICK_BUDGETS if args.quick else FULL_BUDGETS)
    sizes = sized_by_args(RunSizes.quick() if args.quick else CAPTURE, args)
    iters = args.iters or (sizes.iters if args.quick else TrainConfig.iters)
    seeds = seed_list(args)
    jobs = 1 if args.quick else 2
    shards = args.shards or prepare_shards(args.out, prepare_capture(args.out, sizes, 0, args.subject, jobs=jobs),
                                           sizes, jobs=jobs)
    configs = {name: ({**CONFIGS[name], "preset": "tiny"} if args.quick else CONFIGS[name]) for name in names}
    curves = {name: [run_curve(shards, args.out / "runs" / name.replace(" ", "_") / f"seed{s}", fields, iters, s,
                               sizes.eval_frames, args.device) for s in seeds]
              for name, fields in configs.items()}
    quick_fields = {"preset": "tiny"} if args.quick else {}
    for budget in budgets:
        name = f"default, {budget:g} s budget"
        configs[name] = {**quick_fields, "time_budget": budget}
        curves[name] = [run_budget(shards, args.out / "runs" / f"budget_{budget:g}s" / f"seed{s}", budget, s,
                                   sizes.eval_frames, args.device, quick_fields) for s in seeds]
    rows = [_row(name, configs[name], seeds, seeds_points) for name, seeds_points in curves.items()]
    title = "Time to quality" + (" — quick mode" if args.quick else "")
    curve_chart(curves, args.out / "time_to_quality.png", title)
    notes = ["", "| configuration | iterations | train s | validation masked PSNR | validation fg PSNR | validation "
             "FLIP | test masked PSNR | test fg PSNR | test FLIP |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    notes += [f"| {r['name']} | {r['iters']} | {r['train_s']:.0f} | {r['validation_masked_psnr']:.2f} | "
              f"{r['validation_fg_psnr']:.2f} | {r['validation_fg_flip']:.4f} | {r['novel_view_masked_psnr']:.2f} | "
              f"{r['novel_view_fg_psnr']:.2f} | {r['novel_view_fg_flip']:.4f} |" for r in rows]
    notes += ["", f"Means over seeds {seeds}; a time budget's iterations are its seeds' mean; capture "
              f"{sizes.frames} frames, {sizes.cameras} cameras at {sizes.size} px.", "",
              "![time to quality](time_to_quality.png)",
              *(["", "Quick mode: a few iterations; the numbers show the pipeline works."] if args.quick else [])]
    payload = {"title": title, "quick": args.quick, "sizes": dataclasses.asdict(sizes), "seeds": seeds,
               "configurations": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    md = "\n".join([f"# {title}", *notes]) + "\n"
    (args.out / "results.md").write_text(md)
    print(md)
    return payload


if __name__ == "__main__":
    main()
