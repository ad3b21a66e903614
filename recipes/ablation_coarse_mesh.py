"""Ablation e–f of the paper (L1): single- and two-surface models on the original, smoothed and coarse templates.

The paper's "coarse mesh" (table rows e–f, appendix k–l with the perceptual term) is a smoothed
version of the DDC template. Here the capture's character gives three template variants
(``deliffas.data.template_build.build_templates``): ``original``, ``smooth`` (Taubin) and
``coarse`` (decimated, attributes transferred). The SAME subject images are converted once per
variant (``convert --template DIR/VARIANT``) and both models are trained on each with L1 only.
Every configuration is trained with ``--seeds N`` seeds (default 3 in full mode). The report gives
how much foreground PSNR (padded mask box) each model loses against the original template, mean ±
std over seeds, and tests the paper's claim with a margin: on the smoothed template the two-surface
model loses at most 60 % of what the single-surface one loses (the paper: 33.27 -> 32.03 dB against
31.34 -> 29.63 dB, i.e. 73 %); when it fails the report says why with the measured evidence.

Usage: ``python -m recipes.ablation_coarse_mesh --out OUT [--quick] [--seeds N] [--subject DIR | --shards DIR]
[--smooth-iters N] [--coarse-faces N] [--variants original,smooth[,coarse]]`` (full mode trains
original and smooth by default: the claim needs those, and 3 seeds of both fit in ~30 min). With ``--shards`` the images are re-converted from the
subject folder recorded in the shards' manifest (it must still exist).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from recipes.common import (RecipeSizes, ablation_sizes, bar_chart, find_character, prepare_capture, prepare_shards,
                            prepare_template_variants, recipe_parser, seed_list, shards_source, train_and_eval_seeds,
                            write_outputs)
from recipes.seeds import mean

MODELS = (("single-surface", "single_surface"), ("two-surface", "two_surface"))
SMOOTH_ITERS = 300
"""Taubin iterations of the smooth variant: on the procedural character 300 move the surface by
~10 mm on average (25 mm at most), mostly outwards (lambda 0.5 / mu -0.53 inflates slightly per
iteration); 10 iterations move it by < 1 mm, invisible at these image sizes."""
TARGET_RATIO = 0.6
"""The claim's margin: the two-surface model loses at most this fraction of the single-surface model's loss."""
COARSE_FACES = 400
"""Face budget of the coarse variant (the procedural character has 7,652 faces): ~4 mm mean, ~20 mm
largest deviation."""


@dataclasses.dataclass(frozen=True)
class VariantSource:
    """Where the images come from and how to convert them like the given shards."""

    subject: Path
    character: Path
    sizes: RecipeSizes
    offset_mm: float = 30.0
    cameras: tuple[int, ...] | None = None


def variant_source(args, sizes: RecipeSizes) -> VariantSource:
    """The subject to re-convert: ``--subject``, the subject recorded in ``--shards``, or a synthetic capture."""
    if args.shards is not None and args.subject is None:
        cfg = shards_source(args.shards)
        subject = Path(cfg.get("subject") or "")
        if not subject.is_dir():
            raise SystemExit(f"--shards {args.shards}: this ablation converts the same images with other templates and "
                             f"needs the subject folder recorded in the manifest ({subject}), which does not exist; "
                             "pass --subject")
        character = Path(cfg["character"]) if cfg.get("character") else find_character(subject)
        cams = cfg.get("cameras")
        return VariantSource(subject, character, dataclasses.replace(sizes, atlas_res=int(cfg["atlas_res"])),
                             float(cfg.get("offset_mm", 30.0)), tuple(cams) if cams else None)
    subject = prepare_capture(args.out, sizes, 0, args.subject, jobs=1 if args.quick else 2)
    return VariantSource(subject, find_character(subject), sizes)


def template_deviation(variant_character: Path, original_character: Path) -> dict:
    """Symmetric surface distance (mm, rest pose) between a variant's template and the original's."""
    from deliffas.io.formats.dynacap.character import read_character
    from deliffas.geometry.variants import closest_points_on_mesh

    a = read_character(variant_character).mesh
    b = read_character(original_character).mesh
    d_ab = closest_points_on_mesh(a.verts, b.verts, b.faces)[2]
    d_ba = closest_points_on_mesh(b.verts, a.verts, a.faces)[2]
    d = np.concatenate([d_ab, d_ba])
    return {"faces": int(a.num_faces), "verts": int(a.num_verts), "deviation_mean_mm": float(d.mean()),
            "deviation_max_mm": float(d.max())}


def silhouette_errors(shards: Path, max_frames: int = 4) -> dict:
    """How the inner surface's image footprint differs from the person's (training cameras, a few frames).

    ``inner_outside_mask``: pixels the inner surface covers outside the ground-truth mask, and
    ``mask_missed``: mask pixels it does not cover, both as fractions of the mask's pixels. A
    single-surface model paints on the inner surface only: it cannot cover missed pixels, and a
    texel that lies outside the silhouette in one view (target: background) is on the person in another.
    """
    from deliffas.engine.data_bridge import evaluation_samples

    samples, _ = evaluation_samples(str(shards), "train", max_frames=max_frames, with_rays=True, protocol="all")
    outside = missed = fg = 0
    for sample in samples:
        for k, rays in enumerate(sample.rays):
            mask = sample.masks[k].reshape(-1) > 0.5
            hit = np.zeros(mask.size, bool)
            hit[rays.pixels[~rays.inner_from_outer]] = True
            outside += int((hit & ~mask).sum())
            missed += int((~hit & mask).sum())
            fg += int(mask.sum())
    return {"inner_outside_mask": outside / max(fg, 1), "mask_missed": missed / max(fg, 1)}


def run_variants(args, sizes: RecipeSizes, source: VariantSource, variants: dict[str, Path],
                 models=MODELS, seeds=(0,)) -> tuple[list[dict], dict[str, dict]]:
    """Convert the subject with each template variant and train + evaluate each model on it (L1)."""
    geometry = {}
    rows = []
    original = next(iter(Path(variants["original"]).glob("*.character")))
    for variant, folder in variants.items():
        character = next(iter(Path(folder).glob("*.character")))
        geometry[variant] = template_deviation(character, original)
        print(f"template {variant}: {geometry[variant]['faces']} faces, deviation from the original "
              f"{geometry[variant]['deviation_mean_mm']:.1f} mm mean / {geometry[variant]['deviation_max_mm']:.1f} mm max",
              flush=True)
        shards = prepare_shards(args.out, source.subject, source.sizes, name=f"shards_{variant}", template=str(folder),
                                offset_mm=source.offset_mm, cameras=source.cameras, jobs=1 if args.quick else 2)
        geometry[variant].update(silhouette_errors(shards))
        for label, model in models:
            row = train_and_eval_seeds(f"{label} · {variant}", shards, args.out / "runs" / variant / model, sizes, model,
                                       seeds, args.device)
            row.update(template=variant, variant=model, **{f"template_{k}": v for k, v in geometry[variant].items()})
            rows.append(row)
    return rows, geometry


def _paired_loss(base: dict, row: dict, key: str) -> dict:
    """Loss (base - row) per seed of ``key`` (same seed on both templates): mean, sample std, values."""
    import statistics

    values = [a - b for a, b in zip(base["stats"][key]["values"], row["stats"][key]["values"])
              if a is not None and b is not None]
    return {"mean": statistics.fmean(values) if values else None,
            "std": statistics.stdev(values) if len(values) > 1 else 0.0, "values": values}


def losses_against_original(rows: list[dict], models=MODELS) -> dict[str, dict[str, dict]]:
    """{model: {variant: {"psnr_loss_db", "psnr_loss_std_db", "psnr_loss_per_seed", "ssim_loss",
    "official_psnr_loss_db"}}}: foreground PSNR/SSIM lost against the same model and seed on the original
    template (mean over seeds)."""
    by = {(r["variant"], r["template"]): r for r in rows}
    out: dict[str, dict[str, dict]] = {}
    for _, model in models:
        base = by.get((model, "original"))
        if base is None:
            continue
        out[model] = {}
        for (m, t), r in by.items():
            if m != model or t == "original":
                continue
            loss = _paired_loss(base, r, "fg_psnr")
            out[model][t] = {"psnr_loss_db": loss["mean"], "psnr_loss_std_db": loss["std"],
                             "psnr_loss_per_seed": loss["values"],
                             "ssim_loss": mean(base, "fg_ssim") - mean(r, "fg_ssim"),
                             "official_psnr_loss_db": _paired_loss(base, r, "psnr")["mean"]}
    return out


def ratio_claim(losses: dict, geometry: dict, variant: str = "smooth") -> dict:
    """The paper's claim on ``variant``: two-surface loss <= TARGET_RATIO x single-surface loss, with evidence."""
    a = losses["single_surface"][variant]
    b = losses["two_surface"][variant]
    noise = max(a["psnr_loss_std_db"], b["psnr_loss_std_db"])
    single, two = a["psnr_loss_db"], b["psnr_loss_db"]
    out = {"claim": f"two-surface loses <= {TARGET_RATIO:.0%} of single-surface's fg PSNR loss on the {variant} template",
           "single_loss_db": single, "two_loss_db": two, "target_ratio": TARGET_RATIO, "seed_std_db": noise,
           "ratio": two / single if single > 0 else None, "holds": None, "why": None}
    if single <= 0:
        out["why"] = (f"the {variant} template costs the single-surface model nothing ({single:+.2f} dB): there is no loss "
                      f"to reduce; its deviation from the original ({geometry[variant]['deviation_mean_mm']:.1f} mm mean) "
                      "does not show at this image size")
        return out
    out["holds"] = bool(two <= TARGET_RATIO * single)
    if not out["holds"]:
        g, o = geometry[variant], geometry["original"]
        reasons = []
        if single < 2 * noise:
            reasons.append(f"the single-surface loss ({single:.2f} dB) is within twice the seeds' std ({noise:.2f} dB)")
        reasons.append(f"the inner surface misses {100 * g['mask_missed']:.1f}% of the mask (original "
                       f"{100 * o['mask_missed']:.1f}%) and covers {100 * g['inner_outside_mask']:.1f}% outside it "
                       f"(original {100 * o['inner_outside_mask']:.1f}%)")
        out["why"] = "; ".join(reasons)
    return out


def loses_less(single_loss_db: float, two_loss_db: float) -> bool | None:
    """Whether the two-surface model loses less PSNR than the single-surface one; None when neither loses."""
    if max(single_loss_db, two_loss_db) <= 0.0:
        return None
    return bool(two_loss_db < single_loss_db)


def verdict(value: bool | None) -> str:
    return "neither loses" if value is None else ("yes" if value else "no")


def loss_table(losses: dict, geometry: dict, rows: list[dict]) -> list[str]:
    """Markdown: per variant, its geometry, each model's PSNR and its loss against the original."""
    by = {(r["variant"], r["template"]): r for r in rows}
    lines = ["| template | faces | deviation mean / max (mm) | inner surface outside mask / mask missed | "
             "single-surface fg PSNR | two-surface fg PSNR | single-surface loss (dB) | two-surface loss (dB) | "
             "two-surface loses less |",
             "|---|---:|---:|---:|---:|---:|---:|---:|:---:|"]
    for variant, g in geometry.items():
        s, t = by.get(("single_surface", variant)), by.get(("two_surface", variant))
        if variant == "original":
            ls = lt = answer = "—"
        else:
            a = losses.get("single_surface", {}).get(variant, {}).get("psnr_loss_db")
            b = losses.get("two_surface", {}).get(variant, {}).get("psnr_loss_db")
            ls, lt = f"{a:+.2f}", f"{b:+.2f}"
            answer = verdict(loses_less(a, b))
        lines.append(f"| {variant} | {g['faces']:,} | {g['deviation_mean_mm']:.1f} / {g['deviation_max_mm']:.1f} | "
                     f"{100 * g['inner_outside_mask']:.1f}% / {100 * g['mask_missed']:.1f}% | "
                     f"{mean(s, 'fg_psnr'):.2f} | {mean(t, 'fg_psnr'):.2f} | {ls} | {lt} | {answer} |")
    return lines


def main(argv=None) -> dict:
    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--smooth-iters", type=int, default=SMOOTH_ITERS, help="Taubin iterations of the smooth variant")
    p.add_argument("--coarse-faces", type=int, default=COARSE_FACES, help="face budget of the coarse variant")
    p.add_argument("--variants", default=None,
                   help="template variants to train, from original,smooth,coarse (default: all three with --quick; "
                        "original,smooth in full mode, which the paper's claim needs and 3 seeds fit in ~30 min)")
    args = p.parse_args(argv)
    wanted = [v.strip() for v in (args.variants or ("original,smooth,coarse" if args.quick else "original,smooth"))
              .split(",") if v.strip()]
    if "original" not in wanted or "smooth" not in wanted or not set(wanted) <= {"original", "smooth", "coarse"}:
        p.error(f"--variants must include original and smooth, from original,smooth,coarse; got {args.variants!r}")
    sizes = ablation_sizes(args)
    seeds = seed_list(args)
    source = variant_source(args, sizes)
    variants = prepare_template_variants(args.out / "templates", source.character, smooth_iters=args.smooth_iters,
                                         coarse_faces=args.coarse_faces if "coarse" in wanted else None,
                                         offset_mm=source.offset_mm, packing_res=256 if args.quick else 512)
    rows, geometry = run_variants(args, sizes, source, variants, seeds=seeds)
    losses = losses_against_original(rows)
    claims = {}
    for variant in (v for v in variants if v != "original"):
        a = losses["single_surface"][variant]["psnr_loss_db"]
        b = losses["two_surface"][variant]["psnr_loss_db"]
        claims[f"two_surface_loses_less_on_{variant}"] = loses_less(a, b)
    by = {(r["variant"], r["template"]): r for r in rows}
    for variant in variants:
        claims[f"two_surface_beats_single_surface_on_{variant}"] = bool(
            mean(by[("two_surface", variant)], "fg_psnr") > mean(by[("single_surface", variant)], "fg_psnr"))
    claims["paper_ratio_on_smooth"] = ratio = ratio_claim(losses, geometry, "smooth")
    verdict_line = (f"**Paper claim** ({ratio['claim']}): "
                    + ("not testable" if ratio["holds"] is None else ("HOLDS" if ratio["holds"] else "DOES NOT HOLD"))
                    + f" — single-surface loses {ratio['single_loss_db']:+.2f} dB, two-surface {ratio['two_loss_db']:+.2f} dB"
                    + (f" (ratio {ratio['ratio']:.2f}, target <= {TARGET_RATIO})" if ratio["ratio"] is not None else "")
                    + f"; seeds' std {ratio['seed_std_db']:.2f} dB" + (f". Why: {ratio['why']}." if ratio["why"] else "."))
    title = (f"Ablation: template quality ({' / '.join(variants)}), single vs two surfaces, L1"
             + (" — quick mode" if args.quick else ""))
    notes = ["## Foreground PSNR lost against the original template (mean over seeds)", "",
             *loss_table(losses, geometry, rows), "", verdict_line, "",
             (f"Two-surface loses less than single-surface on the coarse template ({args.coarse_faces} faces): "
              f"{verdict(claims['two_surface_loses_less_on_coarse'])}; on" if "coarse" in variants else
              "Two-surface loses less than single-surface on") + " the smooth template "
             f"({args.smooth_iters} Taubin iterations): {verdict(claims['two_surface_loses_less_on_smooth'])}.",
             "Paper (D2, L1): single-surface 31.34 → 29.63 dB (−1.71), two-surface 33.27 → 32.03 dB (−1.24) with the "
             "smoothed (\"coarse\") template, rows a/c vs e/f.",
             "The paper's coarse mesh is a smoothed template: our `smooth` variant matches it; `coarse` (decimated by "
             "quadric edge collapse, which keeps the silhouette, with a new xatlas atlas) is an additional variant that "
             "also changes the uv parametrisation. Deviation: symmetric rest-pose surface distance to the original "
             f"(largest here: {max(geometry, key=lambda v: geometry[v]['deviation_mean_mm'])}).",
             "Silhouette columns: training-camera pixels the inner surface covers outside the person's mask, and mask "
             "pixels it misses, as fractions of the mask (a few frames). The single-surface model can only paint on "
             "the inner surface; the two-surface model also shades the 30 mm shell around it.",
             "Every row: L1 only, the same subject images, iterations, cameras per frame and seed; only the template "
             "(inner surface, its 30 mm shell and uv atlas) changes.",
             *(["Quick mode: a few iterations of the tiny preset; the numbers show the pipeline works, not the "
                "orderings."] if args.quick else []),
             "", "![PSNR per template](psnr_by_template.png)", ""]
    payload = write_outputs(args.out, title, rows, {"quick": args.quick, "sizes": dataclasses.asdict(sizes), "seeds": seeds,
                                                     "convert_sizes": dataclasses.asdict(source.sizes),
                                                     "subject": str(source.subject), "character": str(source.character),
                                                     "smooth_iters": args.smooth_iters, "coarse_faces": args.coarse_faces,
                                                     "templates": geometry, "losses_vs_original": losses,
                                                     "claims": claims}, notes)
    bar_chart(rows, args.out / "psnr_by_template.png", title, key="fg_psnr_mean",
              ylabel="foreground PSNR (dB, padded mask box), mean over seeds", groups=[r["template"] for r in rows])
    return payload


if __name__ == "__main__":
    main()
