"""Where it fails: held-out quality against the number of training cameras and the image size, and the error budget.

Usage: ``python -m recipes.where_it_fails --out OUT [--quick] [--seeds N] [--default-seeds N]
[--cameras-list 4,8,16,32] [--size 256] [--sizes 128,256,512] [--models single_surface,two_surface,default]
[--threshold-db 24]``.

Camera sweep: one synthetic capture with enough cameras (the largest count + a quarter held out as
test cameras), converted once per count with that many training cameras (the test cameras fixed), at
``--size`` (default 256 px; the atlas side follows a given ``--size``).
Size sweep: one capture per image side (atlas side = image side, the recipe capture's other sizes). Captures
are rendered with 3 x 3 rays per pixel (``--supersample`` to change; 1 with ``--quick``).
Every point is trained with the default run's schedule for ``ABLATION_ITERS`` iterations on every shaded ray
(the budget of the documented rows; ``--iters`` to change) over ``--seeds`` (the ``default`` model over ``--default-seeds``) and scored on the held-out
test cameras in masked PSNR (the person's pixels) and foreground PSNR/FLIP. For each model the table
states the smallest camera count and image side at which its masked PSNR stays at or above
``--threshold-db``. The error budget (:mod:`deliffas.models.error_budget`) of the default model at the
camera sweep's largest count says where its remaining error sits: ``error_budget.png`` and a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from deliffas.engine.run_sizes import RunSizes
from deliffas.engine.train_config import TrainConfig
from recipes.common import (ABLATION_ITERS, FULL_SUPERSAMPLE, prepare_capture, prepare_shards, recipe_parser,
                            seed_list, sized_by_args, train_and_eval)

BASE = RunSizes(frames=40, test_frames=10, cameras=12, size=256, atlas_res=256, iters=0, cameras_per_frame=3,
                preset="small", eval_frames=10, supersample=FULL_SUPERSAMPLE)
MODELS = {"single_surface": {"model": "single_surface"}, "two_surface": {"model": "two_surface"},
          "default": {"model": TrainConfig.model}}
"""Model name -> TrainConfig fields (``default``: ``deliffas train``'s defaults)."""


def _ints(text: str, flag: str) -> list[int]:
    try:
        values = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise SystemExit(f"{flag}: expected comma-separated whole numbers, got {text!r}") from None
    if not values or min(values) < 1:
        raise SystemExit(f"{flag}: expected whole numbers >= 1, got {text!r}")
    return sorted(set(values))


def _point(out: Path, shards: Path, sizes: RunSizes, model: str, fields: dict, seeds: list[int], device: str) -> dict:
    """Mean scores over seeds of one model at one point (novel views)."""
    per_seed = []
    for seed in seeds:
        ev = train_and_eval(model, shards, out / model / f"seed{seed}", sizes, fields["model"],
                            seed, device, **{k: v for k, v in fields.items() if k != "model"})
        fg = ev["foreground"]
        per_seed.append({"masked_psnr": fg["masked_psnr"], "fg_psnr": fg["psnr"], "fg_flip": fg["flip"],
                         "run": str(out / model / f"seed{seed}")})
    mean = {k: sum(s[k] for s in per_seed) / len(per_seed) for k in ("masked_psnr", "fg_psnr", "fg_flip")}
    return {**mean, "per_seed": per_seed}


def _sweep_cameras(args, sizes: RunSizes, counts: list[int], seeds: dict[str, list[int]], models: dict) -> dict:
    total = max(counts) + max(1, (max(counts) + 2) // 3)  # a quarter of the rig held out as test cameras
    rig = dataclasses.replace(sizes, cameras=total)
    subject = prepare_capture(args.out / "cameras", rig, 0, jobs=1 if args.quick else 2)
    test = [int(c) for c in (subject / "test_cameras.txt").read_text().split()]
    train = [c for c in range(total) if c not in test]
    result = {}
    for n in counts:
        keep = sorted(test + train[:: max(1, len(train) // n)][:n])
        shards = prepare_shards(args.out / "cameras", subject, rig, name=f"shards_{n}", cameras=keep,
                                jobs=1 if args.quick else 2)
        result[n] = {m: _point(args.out / "cameras" / f"runs_{n}", shards, rig, m, f, seeds[m], args.device)
                     for m, f in models.items()}
    return result


def _sweep_sizes(args, sizes: RunSizes, sides: list[int], seeds: dict[str, list[int]], models: dict) -> dict:
    result = {}
    for side in sides:
        at = dataclasses.replace(sizes, size=side, atlas_res=side)
        root = args.out / f"size_{side}"
        shards = prepare_shards(root, prepare_capture(root, at, 0, jobs=1 if args.quick else 2), at,
                                jobs=1 if args.quick else 2)
        result[side] = {m: _point(root / "runs", shards, at, m, f, seeds[m], args.device) for m, f in models.items()}
    return result


def _first_ok(sweep: dict, model: str, threshold: float):
    """The smallest sweep value at which ``model``'s masked PSNR is >= threshold and stays so above it."""
    keys = sorted(sweep)
    ok = [k for i, k in enumerate(keys) if all(sweep[j][model]["masked_psnr"] >= threshold for j in keys[i:])]
    return ok[0] if ok else None


def _chart(sweep: dict, path: Path, xlabel: str, threshold: float, title: str) -> Path:
    from deliffas.engine.report import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.4, 4.2), dpi=120)
    keys = sorted(sweep)
    for i, model in enumerate(next(iter(sweep.values()))):
        ax.plot(keys, [sweep[k][model]["masked_psnr"] for k in keys], "o-", color=f"C{i}", label=model)
    ax.axhline(threshold, color="k", ls="--", lw=0.8, label=f"threshold {threshold:g} dB")
    ax.set_xscale("log", base=2)
    ax.set_xticks(keys, [str(k) for k in keys])
    ax.set_xlabel(xlabel)
    ax.set_ylabel("masked PSNR (dB), held-out cameras")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside: the lines end top right
    return save_figure(fig, path)


def _budget(args, runs: list[str]) -> dict:
    """The default model's error budget on the held-out cameras, per seed and drawn for the first."""
    from deliffas.engine.error_report import budget_figure, measure_error_budget

    budgets = {f"seed {i}": measure_error_budget(run, "novel_view", max_frames=BASE.eval_frames if not args.quick else 2,
                                                 device=args.device) for i, run in enumerate(runs)}
    budget_figure(budgets, args.out / "error_budget.png", "default model, held-out cameras")
    return budgets


def _budget_table(budget: dict) -> list[str]:
    lines = ["| pixel class | share of pixels | share of masked squared error | PSNR |", "|---|---:|---:|---:|"]
    for name, c in budget["classes"].items():
        if name != "background":
            lines.append(f"| {name} | {c['pixel_share']:.3f} | {c['error_share']:.3f} | "
                         f"{'n/a' if c['psnr'] is None else format(c['psnr'], '.2f')} |")
    lines += ["", "| detail scale | error (mean square) | ground truth's energy | share of the error |",
              "|---|---:|---:|---:|"]
    lines += [f"| {n} | {b['error_ms']:.2e} | {b['gt_ms']:.2e} | {b['error_share']:.3f} |"
              for n, b in budget["bands"].items()]
    return lines


def main(argv=None) -> dict:
    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--cameras-list", default=None, help="training camera counts (default 4,8,16,32; quick 2,3)")
    p.add_argument("--sizes", default=None, help="image sides in px (default 128,256,512; quick 32,64; atlas side = image side, a power of two)")
    p.add_argument("--models", default=None, help=f"comma-separated, of {','.join(MODELS)} (default all)")
    p.add_argument("--default-seeds", type=int, default=None,
                   help="training seeds of the default model (default: --seeds); more seeds where it matters most")
    p.add_argument("--threshold-db", type=float, default=24.0, help="the stated quality, masked PSNR (default 24)")
    args = p.parse_args(argv)
    sizes = sized_by_args(dataclasses.replace(RunSizes.quick(), cameras_per_frame=2) if args.quick else BASE, args)
    if args.size:
        sizes = dataclasses.replace(sizes, atlas_res=args.size)
    if not args.iters and not args.quick:
        sizes = dataclasses.replace(sizes, iters=ABLATION_ITERS)
    names = args.models.split(",") if args.models else list(MODELS)
    if any(n not in MODELS for n in names):
        p.error(f"--models: expected names from {','.join(MODELS)}, got {args.models!r}")
    models = {n: ({**MODELS[n], "preset": "tiny"} if args.quick else MODELS[n]) for n in names}
    counts = _ints(args.cameras_list or ("2,3" if args.quick else "4,8,16,32"), "--cameras-list")
    sides = _ints(args.sizes or ("32,64" if args.quick else "128,256,512"), "--sizes")
    if args.default_seeds is not None and args.default_seeds < 1:
        p.error(f"--default-seeds: expected a whole number >= 1, got {args.default_seeds}")
    seeds = {m: seed_list(args) for m in models}
    if args.default_seeds is not None and "default" in models:
        seeds["default"] = seed_list(argparse.Namespace(quick=args.quick, seed=args.seed, seeds=args.default_seeds))
    cams = _sweep_cameras(args, sizes, counts, seeds, models)
    by_size = _sweep_sizes(args, sizes, sides, seeds, models)
    title = "Where it fails" + (" — quick mode" if args.quick else "")
    _chart(cams, args.out / "cameras.png", "training cameras", args.threshold_db, title)
    _chart(by_size, args.out / "sizes.png", "image side (px)", args.threshold_db, title)
    budget_model = "default" if "default" in models else names[-1]
    budgets = _budget(args, [s["run"] for s in cams[max(counts)][budget_model]["per_seed"]])
    falls = {m: {"cameras": _first_ok(cams, m, args.threshold_db), "size": _first_ok(by_size, m, args.threshold_db)}
             for m in models}
    md = [f"# {title}", "", f"Masked PSNR (dB) on the held-out cameras, mean over seeds "
          f"{'; '.join(f'{m} {s}' for m, s in seeds.items())}; "
          f"{sizes.iters} iterations per run.", "", "| model | " + " | ".join(f"{n} cameras" for n in counts)
          + " | " + " | ".join(f"{s} px" for s in sides) + " | holds >= threshold from |",
          "|---|" + "---:|" * (len(counts) + len(sides)) + "---|"]
    for m in models:
        cells = [f"{cams[n][m]['masked_psnr']:.2f}" for n in counts] + [f"{by_size[s][m]['masked_psnr']:.2f}" for s in sides]
        f = falls[m]
        md.append(f"| {m} | " + " | ".join(cells) + f" | {f['cameras'] or 'never'} cameras, {f['size'] or 'never'} px |")
    md += ["", f"Threshold: {args.threshold_db:g} dB masked PSNR.", "", "![cameras](cameras.png) ![sizes](sizes.png)",
           "", f"## Error budget ({budget_model}, {max(counts)} cameras, first seed)", "",
           *_budget_table(next(iter(budgets.values()))), "", "![error budget](error_budget.png)",
           *(["", "Quick mode: a few iterations; the numbers show the pipeline works."] if args.quick else [])]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.md").write_text("\n".join(md) + "\n")
    payload = {"title": title, "quick": args.quick, "seeds": seeds, "threshold_db": args.threshold_db,
               "cameras": cams, "sizes": by_size, "falls_below": falls, "error_budget": budgets}
    (args.out / "results.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    print("\n".join(md))
    return payload


if __name__ == "__main__":
    main()
