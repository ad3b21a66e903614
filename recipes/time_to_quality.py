"""Time to quality: held-out quality against training wall-clock, the default run against the paper's schedule.

Usage: ``python -m recipes.time_to_quality --out OUT [--quick] [--seeds N] [--iters N]
[--subject DIR | --shards DIR]``.

Each configuration is trained over seeds on the 256 x 256 recipe capture (40 training + 10 test frames,
12 cameras: a quarter held out as test cameras and one training camera as the validation split; rendered with
3 x 3 rays per pixel, ``--supersample`` to change); at
``CHECKPOINTS`` fractions of the run the model is evaluated on the validation camera (foreground and
masked PSNR, FLIP) and on the held-out test cameras. Training seconds exclude the evaluations. Writes
``results.json``, ``results.md`` and ``time_to_quality.png`` (masked PSNR against seconds).

Configurations: ``default`` is ``deliffas train`` without options (``TrainConfig`` defaults:
``two_surface_reflect_texture``); ``two_surface_texture`` the same without the reflected view direction (the
previous default); ``paper schedule`` is the paper's model and schedule (``two_surface``, Adam 2e-4 with the
official decay), the default before this recipe existed.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from deliffas.engine.run_sizes import RunSizes
from recipes.common import FULL_SUPERSAMPLE, prepare_capture, prepare_shards, recipe_parser, seed_list, sized_by_args

CAPTURE = RunSizes(frames=40, test_frames=10, cameras=12, size=256, atlas_res=256, iters=0, cameras_per_frame=3,
                   preset="small", eval_frames=10, supersample=FULL_SUPERSAMPLE)
"""The recipe capture at 256 px, 3 x 3 rays per pixel (``iters`` 0: the configurations' own)."""
CHECKPOINTS = (0.125, 0.25, 0.5, 0.75, 1.0)
"""Fractions of the run at which the model is evaluated."""
CONFIGS: dict[str, dict] = {
    "default": {},
    "two_surface_texture": {"model": "two_surface_texture"},
    "paper schedule": {"model": "two_surface", "schedule": "paper"},
}
"""Name -> TrainConfig fields that differ from ``deliffas train``'s defaults."""


def _scores(ev: dict) -> dict:
    fg = ev["foreground"]
    return {"fg_psnr": fg["psnr"], "masked_psnr": fg.get("masked_psnr"), "fg_flip": fg.get("flip")}


def run_curve(shards: Path, run_dir: Path, fields: dict, iters: int, seed: int, eval_frames: int | None,
              device: str = "cpu") -> list[dict]:
    """Train one configuration, evaluating at ``CHECKPOINTS``; one point per checkpoint (seconds, scores).

    A finished run (``curve.json`` in ``run_dir``) is read back instead of retrained."""
    from deliffas.engine.evaluate import EvalConfig, evaluate
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
        point = {"iteration": mark, "train_s": seconds}
        for split in ("validation", "novel_view"):
            point[split] = _scores(evaluate(EvalConfig(run=str(run_dir), split=split, max_frames=eval_frames,
                                                       device=device)))
        points.append(point)
        print(f"  {run_dir.parent.name} seed {seed}: {mark} it, {seconds:.0f} s, validation masked PSNR "
              f"{point['validation']['masked_psnr']:.2f} dB", flush=True)
    if hasattr(trainer.stream, "close"):
        trainer.stream.close()
    done.write_text(json.dumps(points, indent=1) + "\n")
    return points


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


def main(argv=None) -> dict:
    from deliffas.engine.train_config import TrainConfig

    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--configs", default=None,
                   help=f"comma-separated configurations to run, of {','.join(CONFIGS)} (default all); finished "
                        "runs in OUT are read back, so runs split over processes join in a last call without it")
    args = p.parse_args(argv)
    names = [n.strip() for n in args.configs.split(",")] if args.configs else list(CONFIGS)
    if any(n not in CONFIGS for n in names):
        p.error(f"--configs: expected names from {','.join(CONFIGS)}, got {args.configs!r}")
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
    rows = []
    for name, seeds_points in curves.items():
        finals = [pts[-1] for pts in seeds_points]
        row = {"name": name, "fields": configs[name], "iters": iters, "seeds": seeds, "curves": seeds_points}
        for split in ("validation", "novel_view"):
            for key in ("fg_psnr", "masked_psnr", "fg_flip"):
                values = [f[split][key] for f in finals]
                row[f"{split}_{key}"] = sum(values) / len(values)
        row["train_s"] = sum(f["train_s"] for f in finals) / len(finals)
        rows.append(row)
    title = "Time to quality" + (" — quick mode" if args.quick else "")
    curve_chart(curves, args.out / "time_to_quality.png", title)
    notes = ["", "| configuration | train s | validation masked PSNR | validation fg PSNR | validation FLIP | "
             "test masked PSNR | test fg PSNR | test FLIP |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    notes += [f"| {r['name']} | {r['train_s']:.0f} | {r['validation_masked_psnr']:.2f} | {r['validation_fg_psnr']:.2f} "
              f"| {r['validation_fg_flip']:.4f} | {r['novel_view_masked_psnr']:.2f} | {r['novel_view_fg_psnr']:.2f} "
              f"| {r['novel_view_fg_flip']:.4f} |" for r in rows]
    notes += ["", f"Means over seeds {seeds}; {iters} iterations; capture {sizes.frames} frames, {sizes.cameras} cameras "
              f"at {sizes.size} px.", "", "![time to quality](time_to_quality.png)",
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
