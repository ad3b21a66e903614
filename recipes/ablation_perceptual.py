"""Appendix ablation of the perceptual supervision (two-surface): L1 only, patch-level 32x32 and image-level perceptual.

Every row trains the two-surface model for the same number of iterations: stage 1 with L1, then
(from ``--perceptual-start``) stage 2 with L1 + the VGG-16 perceptual term on 32x32 patches (b) or
on the whole images (c); row (a) stays on L1 throughout. The paper (appendix, table "patch") finds
c better than b on the perceptual metrics (LPIPS 12.85 vs 16.54, FID 8.69 vs 18.96) at equal PSNR.

The ordering is judged on FLIP inside the person's padded mask box (``fg FLIP``, lower is better; a
perceptual metric calibrated on human data that needs no ImageNet network), mean ± std over
``--seeds N`` training seeds (default 3 in full mode): image-level <= patch-level. LPIPS (or its
named substitute) is reported beside it.

The paper's backbone is VGG-16 pre-trained on ImageNet (``--perceptual vgg16-imagenet``, the
default when the weights are found). Without them (no internet here) the recipe says so and uses
``vgg16-random``, a VGG-16 with seeded random weights (Liu et al., "Generic Perceptual Loss"); the
title then names that backbone. LPIPS needs ImageNet weights too: without them it is null with
the reason, and the table shows ``lpips_random_vgg16`` beside it, an LPIPS-style distance on a
random VGG-16 (evaluator seed 0) that is a clearly named substitute, never LPIPS. This recipe trains
with ``--seed 1`` by default so that the random loss network (seed 1) is not the metric's network.

Usage: ``python -m recipes.ablation_perceptual --out OUT [--quick] [--seeds N] [--subject DIR | --shards DIR]
[--perceptual vgg16-imagenet|vgg16-random] [--perceptual-start 0.5]``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from recipes.common import (ablation_sizes, bar_chart, prepare_capture, prepare_shards, recipe_parser, seed_list,
                            train_and_eval_seeds, write_outputs)
from recipes.seeds import mean, ordering

MODEL = "two_surface"
PATCH_PIXELS = 8 * 32 * 32
"""Pixels the patch-level loss looks at per image (``PerceptualLoss`` defaults: 8 patches of 32x32)."""
EVAL_SUBSTITUTE_SEED = 0
"""Seed of the random VGG-16 behind ``lpips_random_vgg16`` (``deliffas.models.metrics.Evaluator`` default)."""
ROWS = (("a. image-level, L1 only", "none", "image"),
        ("b. patch-level 32×32, L1 + perceptual", None, "patch"),
        ("c. image-level, L1 + perceptual (DELIFFAS)", None, "image"))


def imagenet_weights_found(path=None) -> str | None:
    """Path of the ImageNet VGG-16 weights the engine would load, or None."""
    from deliffas.models.vgg import vgg16_weight_candidates

    found = next((c for c in vgg16_weight_candidates(path) if c.is_file()), None)
    return None if found is None else str(found)


def choose_backbone(requested: str | None, vgg16_path=None) -> tuple[str, str]:
    """(backbone name, sentence for the log): the requested one, else ImageNet when found, else random."""
    if requested is not None:
        return requested, f"perceptual backbone: {requested} (requested)"
    found = imagenet_weights_found(vgg16_path)
    if found:
        return "vgg16-imagenet", f"perceptual backbone: vgg16-imagenet ({found})"
    return "vgg16-random", ("ImageNet VGG-16 weights are ABSENT (looked via deliffas.models.vgg.vgg16_weight_candidates); "
                            "using --perceptual vgg16-random, a VGG-16 with seeded random weights. The rows are NOT the "
                            "paper's ImageNet perceptual loss.")


def stage2_record(run: Path) -> dict | None:
    """How stage 2 trained in ``run`` (its ``log.jsonl``): the balanced weight and the weighted perceptual
    term as a fraction of the L1 term at the first and the last logged stage-2 iteration (the paper: the
    two start "roughly the same", so the first share is ~1); None when stage 2 never ran."""
    path = Path(run) / "log.jsonl"
    log = [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []
    stage2 = [r for r in log if r.get("stage") == 2 and r.get("perceptual") is not None and r.get("l1")]
    if not stage2:
        return None

    def share(r):
        return r["perceptual_weight"] * r["perceptual"] / r["l1"]

    return {"from_iteration": stage2[0]["iteration"], "weight": stage2[0]["perceptual_weight"],
            "share_of_l1_first": share(stage2[0]), "share_of_l1_last": share(stage2[-1])}


def backbone_title(backbone: str, seed: int) -> str:
    if backbone == "vgg16-random":
        return f"vgg16-random: VGG-16 random backbone, seed {seed} — not ImageNet"
    return "vgg16-imagenet: VGG-16 ImageNet backbone"


def _parser():
    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--perceptual", choices=("vgg16-imagenet", "vgg16-random"), default=None,
                   help="perceptual backbone (default: vgg16-imagenet when its weights are found, else vgg16-random)")
    p.add_argument("--perceptual-start", type=float, default=0.5,
                   help="fraction of the iterations after which stage 2 (L1 + perceptual) starts")
    p.add_argument("--vgg16-path", default=None, help="ImageNet VGG-16 weight file (else env / torch hub cache)")
    p.set_defaults(seed=1)
    return p


def _train_rows(args, sizes, seeds: list[int], backbone: str, shards, stage2: int) -> list[dict]:
    """One row per configuration of ``ROWS`` (L1 only, patch-level, image-level), trained over ``seeds``."""
    rows = []
    for label, perceptual, mode in ROWS:
        perceptual = perceptual or backbone
        row = train_and_eval_seeds(label, shards, args.out / "runs" / (perceptual if perceptual == "none" else mode),
                                   sizes, MODEL, seeds, args.device, perceptual=perceptual, perceptual_mode=mode,
                                   perceptual_start=args.perceptual_start, vgg16_path=args.vgg16_path)
        row.update(perceptual=perceptual, perceptual_mode=None if perceptual == "none" else mode,
                   stage2_from_iteration=None if perceptual == "none" else stage2,
                   stage2_per_seed=[stage2_record(s["run"]) for s in row["per_seed"]])
        rows.append(row)
    return rows


def _why_not(judged, width: int, height: int, backbone: str) -> list[str]:
    """Reasons the paper's ordering (image-level beats patch-level) does not hold here; empty when it holds."""
    if judged.holds:
        return []
    why = []
    if judged.within_noise:
        why.append(f"the difference is within the seeds' noise (± {judged.noise:.4f} s.e.)")
    coverage = 100 * min(1.0, PATCH_PIXELS / (width * height))
    why.append(f"at {width}×{height} the 8 patches of 32×32 cover up to {coverage:.0f}% of the image, so patch- "
               "and image-level supervision see nearly the same pixels")
    why.append(f"the loss network is {backbone}" + (" (random weights: its features are not ImageNet's)"
                                                    if backbone == "vgg16-random" else ""))
    return why


def main(argv=None) -> dict:
    p = _parser()
    args = p.parse_args(argv)
    if not 0.0 < args.perceptual_start < 1.0:
        p.error(f"--perceptual-start must be in (0, 1), got {args.perceptual_start}")
    sizes = ablation_sizes(args)
    seeds = seed_list(args)
    backbone, message = choose_backbone(args.perceptual, args.vgg16_path)
    print(message, flush=True)
    jobs = 1 if args.quick else 2
    shards = args.shards or prepare_shards(args.out, prepare_capture(args.out, sizes, 0, args.subject, jobs=jobs),
                                           sizes, jobs=jobs)
    stage2 = int(args.perceptual_start * sizes.iters)
    rows = _train_rows(args, sizes, seeds, backbone, shards, stage2)
    a, b, c = rows
    width, height = a["resolution"]
    lpips_ok = all(r.get("lpips") is not None for r in rows)
    metric = "lpips" if lpips_ok else "lpips_random_vgg16"
    metric_name = "LPIPS" if lpips_ok else f"lpips_random_vgg16 (substitute: random VGG-16, seed {EVAL_SUBSTITUTE_SEED})"
    judged = ordering("image-level <= patch-level (fg FLIP, lower is better)", c, b, "fg_flip", 0.0,
                      higher_is_better=False)
    vs_l1 = ordering("image-level <= L1 only (fg FLIP)", c, a, "fg_flip", 0.0, higher_is_better=False)
    psnr_kept = ordering("image-level >= patch-level - 0.5 dB (fg PSNR)", c, b, "fg_psnr", -0.5)
    claims = {"perceptual_metric": "fg_flip", "lpips_family_metric": metric,
              "image_le_patch_on_flip": judged.to_dict(), "image_le_l1_on_flip": vs_l1.to_dict(),
              "image_keeps_fg_psnr": psnr_kept.to_dict(),
              "image_beats_patch_on_perceptual_metric": judged.holds,
              "image_beats_l1_on_perceptual_metric": vs_l1.holds,
              "patch_beats_l1_on_perceptual_metric": bool((mean(b, "fg_flip") or 0) < (mean(a, "fg_flip") or 0)),
              "image_beats_patch_on_lpips_family": bool(c[metric] < b[metric]),
              "image_beats_patch_on_psnr": bool(mean(c, "fg_psnr") > mean(b, "fg_psnr"))}
    why = _why_not(judged, width, height, backbone)
    shared_net = backbone == "vgg16-random" and EVAL_SUBSTITUTE_SEED in seeds and not lpips_ok
    title = (f"Ablation: perceptual supervision, patch vs image level (two-surface; {backbone_title(backbone, args.seed)})"
             + (" — quick mode" if args.quick else ""))
    notes = ["## The paper's ordering", "", f"- {judged.sentence('')}", f"- {vs_l1.sentence('')}",
             f"- {psnr_kept.sentence()}", *([f"- Why it does not hold here: {'; '.join(why)}."] if why else []), "",
             f"Perceptual backbone of the loss: `{backbone}`"
             + (f" (seed {args.seed}); ImageNet weights were not found." if backbone == "vgg16-random" else "."),
             "Perceptual metric used for the comparison: fg FLIP (mean ± std over seeds above); beside it "
             f"{metric_name}"
             + ("" if lpips_ok else f"; LPIPS itself is null ({rows[0].get('lpips_reason')})") + ".",
             f"First seed, image-level beats patch-level on {metric}: {'yes' if claims['image_beats_patch_on_lpips_family'] else 'no'} "
             f"({c[metric]:.4g} vs {b[metric]:.4g}); image-level beats L1 only: "
             f"{'yes' if c[metric] < a[metric] else 'no'} (L1 only: {a[metric]:.4g}).",
             "Stage 2 as trained (first seed; weighted perceptual term / L1 term at its first and last logged "
             "iteration, ~1 at the start by construction): " + "; ".join(
                 f"{r['name'][:2]} weight {st['weight']:.4g}, share {st['share_of_l1_first']:.2f} → "
                 f"{st['share_of_l1_last']:.2f}" for r in (b, c) for st in r["stage2_per_seed"][:1] if st) + ".",
             "Paper (D2, ImageNet VGG-16): LPIPS×1000 L1 18.51, patch 16.54, image 12.85; PSNR 33.27 / 33.24 / 33.30.",
             f"All rows: two-surface, {sizes.iters} iterations, stage 2 from iteration {stage2} "
             f"(perceptual weight balanced with L1 when stage 2 starts); patches: 8 random 32×32 per image "
             f"centred in the foreground box, images {width}×{height}: the patches cover up to "
             f"{100 * min(1.0, PATCH_PIXELS / (width * height)):.0f}% of the image (the paper's 1285×940 images: 0.7%), so "
             "patch- and image-level supervision differ less the smaller the images are.",
             *(["WARNING: the substitute metric's random VGG-16 is the training loss's network (both seed 0): the metric "
                "is partly the training objective. Use --seed other than 0."] if shared_net else []),
             *(["Quick mode: a few iterations of the tiny preset on 48×48 images, where a 32×32 patch covers most of "
                "the image; the numbers show the pipeline works, not the ordering."] if args.quick else []),
             "", f"![{metric} per row](perceptual_metric.png)", "", "![PSNR per row](psnr.png)", ""]
    payload = write_outputs(args.out, title, rows, {"quick": args.quick, "sizes": dataclasses.asdict(sizes), "seeds": seeds,
                                                     "perceptual_backbone": backbone, "backbone_message": message,
                                                     "perceptual_start": args.perceptual_start,
                                                     "substitute_metric_seed": EVAL_SUBSTITUTE_SEED,
                                                     "claims": claims}, notes)
    bar_chart(rows, args.out / "perceptual_metric.png", title, key="fg_flip_mean",
              ylabel="foreground FLIP ↓ (mean over seeds)")
    bar_chart(rows, args.out / "psnr.png", title, key="fg_psnr_mean", ylabel="foreground PSNR (dB), mean over seeds")
    return payload


if __name__ == "__main__":
    main()
