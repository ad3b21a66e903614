"""Speed against accuracy: every variant and several capacities on one chart, with the Pareto front.

Usage: ``python -m recipes.speed_accuracy --out OUT [--quick] [--seeds N] [--subject DIR | --shards DIR]``.

Points, all trained with the same iterations (L1 only) and evaluated on the held-out cameras, each with
``--seeds N`` training seeds (default 3 in full mode; accuracy is the mean ± std over them in foreground
PSNR/SSIM/FLIP inside the person's padded mask box, the official protocol's PSNR beside it):

* the four zoo variants at the recipe's preset (``tiny`` in quick mode, ``small`` otherwise);
* the two-surface model (DELIFFAS) with one knob changed at a time: MLP depth x width, U-Net
  base/max channels, uv-map (atlas) side S (the capture converted again at that ``--atlas-res``)
  and template resolution (coarse variants of the character from ``build_templates``, converted
  with ``--template``).

Cost is milliseconds per frame of one camera (uv ray casting + U-Net(s) + feature sampling + MLP,
``deliffas eval``'s stage timing) at the capture's image size, on this machine's CPU. The Pareto
front (``deliffas.engine.report.pareto_front``) holds the points no other point beats in both lower
cost and higher foreground PSNR (mean over seeds); with LPIPS weights available a second chart does the
same for LPIPS (first seed). Cost is timed on the first seed's run.
Writes ``results.json``, ``results.md``, ``speed_accuracy.png`` (and ``speed_lpips.png``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from recipes.common import (find_character, prepare_capture, prepare_shards, prepare_template_variants,
                            recipe_parser, seed_list, shards_source, sizes_from_args, train_and_eval_seeds)
from recipes.seeds import stats_table

logger = logging.getLogger(__name__)

VARIANTS = ("single_surface", "single_surface_viewdir", "single_surface_two_unet", "two_surface")
KNOB_MODEL = "two_surface"
HEADLINE = "fg_psnr_mean"
"""Accuracy of a point: foreground PSNR (padded mask box), mean over the training seeds."""
SEED_KEYS = ("fg_psnr", "fg_ssim", "fg_flip", "psnr")
"""Metrics of the mean ± std table (no novel-pose or fit evaluation here)."""


@dataclass(frozen=True)
class SweepPlan:
    """The capacities swept around the preset (each list changes one knob of the two-surface model)."""

    mlp: tuple[tuple[int, int], ...]
    """(depth, width) of the light-field MLP; features enter after hidden layer depth // 2."""
    unet: tuple[tuple[int, int], ...]
    """(base_channels, max_channels) of the U-Nets."""
    atlas: tuple[int, ...]
    """Atlas sides S besides the capture's own (each needs one more conversion)."""
    coarse: tuple[float, ...]
    """Face budgets of coarse templates as fractions of the character's faces."""

    @staticmethod
    def for_mode(quick: bool) -> "SweepPlan":
        if quick:  # tiny preset: MLP 2 x 32, U-Net 4 -> 16, S = 32
            return SweepPlan(mlp=((4, 64),), unet=((8, 32),), atlas=(16,), coarse=(0.15,))
        # small preset: MLP 4 x 64, U-Net 8 -> 64, S = 128
        return SweepPlan(mlp=((2, 32), (4, 32), (4, 128), (8, 64), (8, 128)),
                         unet=((4, 32), (16, 128), (32, 256)), atlas=(64, 256), coarse=(0.5, 0.2, 0.05))


@dataclass(frozen=True)
class Point:
    """One configuration of the chart."""

    name: str
    knob: str
    """``variant``, ``mlp``, ``unet``, ``atlas`` or ``template``."""
    model: str
    overrides: dict = field(default_factory=dict)
    shards_key: str = "base"
    """Which conversion: ``base``, ``atlas<S>`` or ``coarse<faces>``."""


def _points(plan: SweepPlan, atlas_sides: list[int], coarse_faces: list[int]) -> list[Point]:
    pts = [Point(f"{v}", "variant", v) for v in VARIANTS]
    for depth, width in plan.mlp:
        pts.append(Point(f"{KNOB_MODEL} mlp {depth}x{width}", "mlp", KNOB_MODEL,
                         {"mlp": {"depth": depth, "width": width, "feature_layer": depth // 2}}))
    for base, top in plan.unet:
        pts.append(Point(f"{KNOB_MODEL} unet {base}-{top}", "unet", KNOB_MODEL,
                         {"unet": {"base_channels": base, "max_channels": top}}))
    for s in atlas_sides:
        pts.append(Point(f"{KNOB_MODEL} S={s}", "atlas", KNOB_MODEL, shards_key=f"atlas{s}"))
    for n in coarse_faces:
        pts.append(Point(f"{KNOB_MODEL} coarse {n} faces", "template", KNOB_MODEL, shards_key=f"coarse{n}"))
    return pts


def _error_row(point: Point, exc: BaseException) -> dict:
    return {"name": point.name, "model": point.model, "psnr": None, "ssim": None, "lpips": None, HEADLINE: None,
            "stage_ms": None,
            "fps": None, "num_parameters": None, "error": f"{type(exc).__name__}: {exc}",
            "traceback": traceback.format_exc(limit=6)}


def total_ms(row: dict) -> float | None:
    """Milliseconds per frame (one camera): the sum of the evaluation's stage times, None after an error."""
    s = row.get("stage_ms")
    return None if not s else float(sum(s.values()))


def _usable(row: dict, key: str) -> bool:
    v = row.get(key)
    return row.get("error") is None and v is not None and math.isfinite(v) and total_ms(row) is not None


def mark_pareto(rows: list[dict], key: str = HEADLINE, higher_is_better: bool = True, flag: str = "pareto") -> None:
    """Set ``row[flag]`` to whether the row is on the (cost = ms per frame, quality = ``key``) Pareto front;
    rows without a usable value get None."""
    from deliffas.engine.report import pareto_front

    idx = [i for i, r in enumerate(rows) if _usable(r, key)]
    sign = 1.0 if higher_is_better else -1.0
    front = set(int(idx[j]) for j in pareto_front([total_ms(rows[i]) for i in idx], [sign * rows[i][key] for i in idx]))
    for i, r in enumerate(rows):
        r[flag] = (i in front) if i in idx else None


def _fmt(v, spec: str = ".2f") -> str:
    return "n/a" if v is None else format(v, spec)


def markdown_table(rows: list[dict]) -> str:
    lines = ["| configuration | knob | params | fg PSNR ↑ (mean) | official PSNR ↑ | official SSIM ↑ | LPIPS ↓ | "
             "uv ms | cnn ms | sample ms | mlp ms | ms/frame | fps | on Pareto front |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:---:|"]
    for r in rows:
        s = r.get("stage_ms") or {}
        if r.get("error"):
            lines.append(f"| {r['name']} | {r.get('knob', '')} | | error: {r['error'][:80]} | | | | | | | | | | |")
            continue
        params = r.get("num_parameters")
        lines.append(f"| {r['name']} | {r.get('knob', '')} | {params:,} | {_fmt(r.get(HEADLINE))} | "
                     f"{_fmt(r.get('psnr'))} | "
                     f"{_fmt(r.get('ssim'), '.4f')} | {_fmt(r.get('lpips'), '.4f')} | {_fmt(s.get('uv'), '.1f')} | "
                     f"{_fmt(s.get('cnn'), '.1f')} | {_fmt(s.get('sample'), '.1f')} | {_fmt(s.get('mlp'), '.1f')} | "
                     f"{_fmt(total_ms(r), '.1f')} | {_fmt(r.get('fps'))} | {'yes' if r.get('pareto') else 'no'} |")
    return "\n".join(lines) + "\n"


def chart(rows: list[dict], path: Path, title: str, resolution: str, key: str = HEADLINE,
          higher_is_better: bool = True, ylabel: str = "fg PSNR (dB), held-out cameras, mean over seeds",
          flag: str = "pareto") -> Path:
    """Quality against ms per frame, coloured by knob, the Pareto front drawn and its points ringed."""
    from deliffas.engine.report import pyplot, save_figure

    plt = pyplot()

    ok = [r for r in rows if _usable(r, key)]
    knobs = list(dict.fromkeys(r.get("knob", "") for r in ok))
    palette = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(7.2, 4.8), dpi=120)
    for k, knob in enumerate(knobs):
        pts = [r for r in ok if r.get("knob", "") == knob]
        ax.scatter([total_ms(r) for r in pts], [r[key] for r in pts], color=palette(k % 10), label=knob, zorder=3)
    for r in ok:
        ax.annotate(r["name"].replace(f"{KNOB_MODEL} ", ""), (total_ms(r), r[key]), textcoords="offset points",
                    xytext=(4, 3), fontsize=6)
    front = sorted((r for r in ok if r.get(flag)), key=total_ms)
    if front:
        ax.plot([total_ms(r) for r in front], [r[key] for r in front], "--", color="tab:red", zorder=2,
                label="Pareto front")
        ax.scatter([total_ms(r) for r in front], [r[key] for r in front], s=140, facecolors="none",
                   edgecolors="tab:red", zorder=4)
    failed = [r["name"] for r in rows if r.get("error")]
    if failed:
        ax.text(0.01, 0.01, "errors: " + ", ".join(failed), transform=ax.transAxes, fontsize=6, color="tab:red")
    ax.set_xlabel(f"ms per frame (uv + cnn + sample + mlp), one camera at {resolution}, CPU")
    ax.set_ylabel(ylabel)
    if not higher_is_better:
        ax.invert_yaxis()
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return save_figure(fig, path)


def retime(timed: list[tuple[dict, Path]], repeats: int, device: str = "cpu") -> None:
    """Time every run ``repeats - 1`` more times, round-robin, and keep each stage's minimum ms.

    Each round evaluates every run once on one frame, so a burst of load from other processes
    falls on all configurations alike rather than on whichever trained last; other processes only
    ever add time, so the minimum over rounds is the steadier estimate. Sets ``stage_ms``, ``fps``,
    ``stage_ms_first`` (the first evaluation's) and ``timing_repeats`` of each row.
    """
    from deliffas.engine.evaluate import EvalConfig, evaluate

    for row, _ in timed:
        row["stage_ms_first"] = dict(row["stage_ms"])
    for _ in range(max(repeats, 1) - 1):
        for row, run in timed:
            try:
                again = evaluate(EvalConfig(run=str(run), split=row.get("split", "novel_view"), max_frames=1,
                                            device=device))
            except Exception as exc:  # timing only: keep what was measured
                logger.warning("re-timing %s failed: %s", run, exc)
                continue
            row["stage_ms"] = {k: min(v, again.stage_ms.get(k, v)) for k, v in row["stage_ms"].items()}
    for row, _ in timed:
        total = sum(row["stage_ms"].values())
        row.update(fps=1000.0 / total if total > 0 else None, timing_repeats=max(repeats, 1),
                   ms_per_frame=total)


def _coarse_budgets(character: Path, fractions: tuple[float, ...]) -> list[int]:
    from deliffas.io.formats.dynacap.character import read_character

    faces = read_character(character).mesh.num_faces
    return sorted({max(64, int(round(f * faces))) for f in fractions}, reverse=True)


def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    sizes = sizes_from_args(args)
    seeds = seed_list(args)
    plan = SweepPlan.for_mode(args.quick if args.plan == "auto" else args.plan == "quick")
    jobs = 1 if args.quick else 2
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.shards:
        base = Path(args.shards)
        source = shards_source(base)
        subject = Path(args.subject or source.get("subject"))
        base_atlas = int(source.get("atlas_res", sizes.atlas_res))
        character = Path(source["character"]) if source.get("character") else find_character(subject)
    else:
        subject = prepare_capture(out, sizes, args.seed, args.subject, jobs=jobs)
        base = prepare_shards(out, subject, sizes, jobs=jobs)
        base_atlas = sizes.atlas_res
        character = find_character(subject)
    sizes = dataclasses.replace(sizes, atlas_res=base_atlas)
    atlas_sides = [s for s in plan.atlas if s != base_atlas]
    coarse = _coarse_budgets(character, plan.coarse)
    points = _points(plan, atlas_sides, coarse)

    shards: dict[str, Path | Exception] = {"base": base}

    def shards_for(key: str) -> Path:
        if key not in shards:
            try:
                if key.startswith("atlas"):
                    s = int(key[len("atlas"):])
                    shards[key] = prepare_shards(out, subject, dataclasses.replace(sizes, atlas_res=s),
                                                 name=f"shards_{key}", jobs=jobs)
                else:
                    n = int(key[len("coarse"):])
                    folders = prepare_template_variants(out / "templates" / key, character, coarse_faces=n,
                                                        packing_res=128 if args.quick else 512)
                    shards[key] = prepare_shards(out, subject, sizes, name=f"shards_{key}",
                                                 template=str(folders["coarse"]), jobs=jobs)
            except Exception as exc:  # recorded on every point that needs these shards
                logger.exception("shards %s failed", key)
                shards[key] = exc
        if isinstance(shards[key], Exception):
            raise shards[key]
        return shards[key]

    rows = []
    timed: list[tuple[dict, Path]] = []
    for p in points:
        try:
            run = out / "runs" / p.name.replace(" ", "_")
            row = train_and_eval_seeds(p.name, shards_for(p.shards_key), run, sizes, p.model, seeds, args.device,
                                       extra_splits=False, model_overrides=p.overrides)
            timed.append((row, run / f"seed{seeds[0]}"))  # the cost does not depend on the seed
        except Exception as exc:  # one broken configuration never stops the study
            logger.exception("%s failed", p.name)
            print(f"  {p.name}: ERROR {type(exc).__name__}: {exc}", flush=True)
            row = _error_row(p, exc)
        row.update(knob=p.knob, overrides=p.overrides, shards=str(shards.get(p.shards_key, "")),
                   ms_per_frame=total_ms(row))
        rows.append(row)
    retime(timed, args.timing_repeats, args.device)
    return _report(rows, out, args, sizes, plan, seeds)


def _report(rows: list[dict], out: Path, args, sizes, plan, seeds: list[int]) -> dict:
    """Mark the Pareto fronts, draw the charts, write results.json and results.md; the payload."""
    mark_pareto(rows, HEADLINE, True, "pareto")
    have_lpips = any(_usable(r, "lpips") for r in rows)
    if have_lpips:
        mark_pareto(rows, "lpips", False, "pareto_lpips")
    res = next((r.get("resolution") for r in rows if r.get("resolution")), None)
    resolution = f"{res[0]}x{res[1]} px" if res else "the capture's size"
    title = "Speed vs accuracy" + (" — quick mode" if args.quick else "")
    charts = {"psnr": str(chart(rows, out / "speed_accuracy.png", f"{title} (foreground PSNR)", resolution))}
    if have_lpips:
        charts["lpips"] = str(chart(rows, out / "speed_lpips.png", f"{title} (LPIPS)", resolution, "lpips", False,
                                    "LPIPS (VGG), held-out cameras", "pareto_lpips"))
    lpips_reason = next((r.get("lpips_reason") for r in rows if r.get("lpips") is None and r.get("lpips_reason")), None)
    front = [r["name"] for r in sorted((r for r in rows if r.get("pareto")), key=total_ms)]
    notes = [f"Cost: ms per frame of one camera at {resolution} (uv ray casting + U-Net(s) + sampling + MLP; "
             f"the U-Net is paid once per frame), {args.device}; each stage is the minimum over "
             f"{args.timing_repeats} timed evaluations, rounds taken over all points in turn (other jobs may "
             "share the CPU).",
             f"Pareto front (foreground PSNR, mean over seeds {seeds}): {' → '.join(front) if front else 'empty'}.",
             f"Preset {sizes.preset}; {sizes.iters} iterations per point and seed; knob rows change one thing of "
             f"{KNOB_MODEL}.",
             "LPIPS: " + ("available (second chart)" if have_lpips else f"unavailable ({lpips_reason})")]
    payload = {"title": title, "quick": args.quick, "sizes": dataclasses.asdict(sizes), "resolution": res,
               "plan": dataclasses.asdict(plan), "seeds": seeds, "pareto_front": front, "charts": charts, "results": rows,
               "command": " ".join(sys.argv)}
    (out / "results.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    seeded = [r for r in rows if "stats" in r]
    md = [f"# {title}", "", markdown_table(rows), "", *[f"- {n}" for n in notes], "",
          "## Mean ± std over training seeds (foreground metrics: the headline)", "",
          *stats_table(seeded, SEED_KEYS), "",
          "![speed vs accuracy](speed_accuracy.png)", ""]
    if have_lpips:
        md += ["![speed vs LPIPS](speed_lpips.png)", ""]
    (out / "results.md").write_text("\n".join(md))
    print("\n".join(md))
    return payload


def _parser():
    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--plan", choices=["auto", "quick", "full"], default="auto",
                   help="capacities swept: quick (one per knob) or full; auto follows --quick")
    p.add_argument("--timing-repeats", type=int, default=3,
                   help="timed evaluations per point; each stage keeps its minimum (shared CPUs only add time)")
    return p


if __name__ == "__main__":
    main()
