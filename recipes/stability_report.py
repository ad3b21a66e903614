"""The stability recipe's report: which rows fail, one chart per sweep, and the markdown tables
(:mod:`recipes.stability` measures the rows)."""

from __future__ import annotations

import math
from pathlib import Path

from recipes.seeds import format_stat

HEADLINE = "fg_psnr_mean"
"""The number a row is judged on: foreground PSNR (padded mask box), mean over the training seeds."""

X_LABELS = {"offset": "outer-shell offset d (mm)", "smoothing": "template smoothing (Taubin iterations)",
            "cameras": "training cameras", "pose_distance": "test pose distance to nearest training pose (DOF units)",
            "holes": "holes in the template"}


# ------------------------------------------------------------------------------------------------ verdicts
def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def mark_failures(rows: list[dict], fail_db: float) -> dict:
    """Set ``failed``, ``drop_db`` and ``best_psnr`` per row; returns {sweep: {variant: [failing labels]}}."""
    summary: dict = {}
    for sweep in dict.fromkeys(r["sweep"] for r in rows):
        for v in dict.fromkeys(r["variant"] for r in rows if r["sweep"] == sweep):
            group = [r for r in rows if r["sweep"] == sweep and r["variant"] == v]
            finite = [r[HEADLINE] for r in group if r.get("error") is None and _finite(r.get(HEADLINE))]
            best = max(finite) if finite else None
            fails = []
            for r in group:
                ok = r.get("error") is None and _finite(r.get(HEADLINE))
                r["best_psnr"] = best
                r["drop_db"] = (best - r[HEADLINE]) if ok and best is not None else None
                r["failed"] = (not ok) or r["drop_db"] > fail_db
                if r["failed"]:
                    why = "error" if r.get("error") else ("non-finite PSNR" if not ok else f"-{r['drop_db']:.2f} dB")
                    fails.append(f"{r['label']}{' ' + r['series'] if r['series'] else ''} ({why})")
            summary.setdefault(sweep, {})[v] = fails
    return summary


def sweep_chart(rows: list[dict], sweep: str, path: Path, title: str, fail_db: float) -> Path:
    from deliffas.engine.report import pyplot, save_figure

    plt = pyplot()

    palette = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    series = list(dict.fromkeys(r["series"] for r in rows))
    styles = ["-o", "--s", ":^"]
    finite = [r[HEADLINE] for r in rows if _finite(r.get(HEADLINE))]
    floor = (min(finite) - 1.0) if finite else 0.0
    for i, v in enumerate(variants):
        for j, s in enumerate(series):
            pts = sorted((r for r in rows if r["variant"] == v and r["series"] == s), key=lambda r: r["value"])
            good = [r for r in pts if r.get("error") is None and _finite(r.get(HEADLINE))]
            if good:
                ax.errorbar([r["value"] for r in good], [r[HEADLINE] for r in good],
                            yerr=[r["stats"]["fg_psnr"]["std"] or 0.0 for r in good], fmt=styles[j % 3],
                            color=palette(i % 10), capsize=3, label=f"{v}" + (f" ({s} shell)" if s else ""), zorder=3)
            bad = [r for r in good if r.get("failed")]
            if bad:
                ax.scatter([r["value"] for r in bad], [r[HEADLINE] for r in bad], marker="x", s=90, color="tab:red",
                           zorder=4)
            for r in pts:
                if r.get("error") is not None or not _finite(r.get(HEADLINE)):
                    ax.scatter([r["value"]], [floor], marker="X", s=90, color=palette(i % 10), zorder=4)
                    ax.annotate("error", (r["value"], floor), textcoords="offset points", xytext=(3, 3), fontsize=7,
                                color="tab:red")
    ax.scatter([], [], marker="x", color="tab:red", label=f"fails (> {fail_db:g} dB below best, or error)")
    ax.set_xlabel(X_LABELS.get(sweep, sweep))
    ax.set_ylabel("fg PSNR (dB), held-out cameras\nmean ± std over seeds")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return save_figure(fig, path)


def _fmt(v, spec: str = ".2f") -> str:
    return "n/a" if not _finite(v) else format(v, spec)


def _extra_text(r: dict) -> str:
    parts = []
    if r["sweep"] == "offset" and r.get("shell"):
        sh = r["shell"]
        parts.append(f"shell self-intersecting faces {sh.get('num_self_intersecting_faces')}")
        if sh.get("offset_min_mm") is not None and r["series"] == "safe":
            parts.append(f"d min/mean {sh['offset_min_mm']:.1f}/{sh['offset_mean_mm']:.1f} mm")
    if r["sweep"] == "holes":
        if "no_exit_fraction" in r:
            parts.append(f"{r.get('faces_deleted', 0)} faces deleted; no exit hit {100 * r['no_exit_fraction']:.2f}% "
                         f"of shell rays, unshaded {100 * r['unshaded_fraction']:.2f}%, person pixels unshaded "
                         f"{100 * r['person_unshaded_fraction']:.2f}%")
        elif r.get("exit_stats_error"):
            parts.append(f"exit stats: {r['exit_stats_error']}")
    if r["sweep"] == "pose_distance" and r.get("test_frames") is not None:
        parts.append(f"{r.get('images')} images, frames {r['test_frames']}")
    if r["sweep"] == "cameras" and r.get("train_cameras") is not None:
        parts.append(f"train cameras {r['train_cameras']}")
    if r.get("note"):
        parts.append(r["note"])
    if r.get("error"):
        parts.append(f"error: {r['error'][:160]}")
    return "; ".join(parts)


def markdown(rows: list[dict], summary: dict, fail_db: float) -> list[str]:
    md = []
    for sweep in dict.fromkeys(r["sweep"] for r in rows):
        md += [f"## {sweep}", "", f"![{sweep}](stability_{sweep}.png)", "",
               "| value | shell | variant | seeds | fg PSNR ↑ | fg SSIM ↑ | fg FLIP ↓ | official PSNR ↑ | "
               "below best (dB) | fails | details |",
               "|---|---|---|---:|---:|---:|---:|---:|---:|:---:|---|"]
        for r in (r for r in rows if r["sweep"] == sweep):
            stats = r.get("stats") or {}
            md.append(f"| {r['label']} | {r['series']} | {r['variant']} | {len(r.get('seeds') or [])} | "
                      + " | ".join(format_stat(stats[k], spec) if k in stats else "n/a"
                                   for k, spec in (("fg_psnr", ".2f"), ("fg_ssim", ".4f"), ("fg_flip", ".4f"),
                                                   ("psnr", ".2f")))
                      + f" | {_fmt(r.get('drop_db'))} | "
                      f"{'**yes**' if r['failed'] else 'no'} | "
                      f"{_extra_text(r)} |")
        md += [""] + [f"- {v} fails at: {', '.join(f) if f else 'nothing in this sweep'}"
                      for v, f in summary.get(sweep, {}).items()] + [""]
    return md
