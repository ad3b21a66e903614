"""Markdown reports and speed-vs-accuracy charts of evaluated runs (used by the demo and the recipes)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["results_table", "protocol_notes", "fg", "pareto_front", "speed_accuracy_chart", "pyplot", "save_figure"]


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (no display on servers and CI)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path) -> Path:
    """Lay out ``fig``, write it to ``path`` (format from the suffix, parent folders created) and
    close it. The file appears complete or not at all: it is written next to ``path`` and renamed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fig.tight_layout()
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        pyplot().close(fig)
    return path


def _fmt(v, spec: str = ".2f") -> str:
    return "n/a" if v is None else format(v, spec)


def fg(row: dict, key: str):
    """``row["foreground"][key]`` of an eval dict (None when absent)."""
    return (row.get("foreground") or {}).get(key)


def protocol_notes(rows: Sequence[dict]) -> list[str]:
    """Markdown lines naming the protocol behind each column of :func:`results_table`."""
    first = rows[0] if rows else {}
    notes = ["Protocols: **fg** = " + str(fg(first, "protocol") or "foreground (padded mask box)")
             + "; **masked** = over the mask pixels only; **official** = "
             + str(first.get("metric_protocol") or "the paper's (white composite, 600x496 crop)")
             + ". FLIP: " + str(first.get("flip_protocol") or "LDR-FLIP, lower is better") + "."]
    reasons = {r.get("lpips_reason") for r in rows if r.get("lpips") is None and r.get("lpips_reason")}
    if reasons:
        notes.append("LPIPS unavailable: " + "; ".join(sorted(reasons)))
    warnings = sorted({w for r in rows for w in r.get("warnings") or ()})
    if warnings:
        notes.append("Warnings: " + "; ".join(warnings))
    return notes


def results_table(rows: Sequence[dict], title: str | None = None) -> str:
    """A markdown table of evaluation results (``deliffas eval --json`` dicts with a ``name``), foreground
    metrics first, each column naming its protocol, with the protocol notes below."""
    lines = [f"### {title}", ""] if title else []
    lines += ["| model | params | fg PSNR ↑ | fg SSIM ↑ | fg FLIP ↓ | masked PSNR ↑ | fg LPIPS ↓ | official PSNR ↑ | "
              "official SSIM ↑ | LPIPS (random VGG, substitute) ↓ | uv ms | cnn ms | sample ms | mlp ms | fps |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        s = r.get("stage_ms", {})
        lines.append(
            f"| {r.get('name', r.get('model'))} | {r.get('num_parameters', 0):,} | {_fmt(fg(r, 'psnr'))} | "
            f"{_fmt(fg(r, 'ssim'), '.4f')} | {_fmt(fg(r, 'flip'), '.4f')} | {_fmt(fg(r, 'masked_psnr'))} | "
            f"{_fmt(fg(r, 'lpips'), '.4f')} | {_fmt(r.get('psnr'))} | {_fmt(r.get('ssim'), '.4f')} | "
            f"{_fmt(r.get('lpips_random_vgg16'), '.5f')} | {_fmt(s.get('uv'), '.1f')} | {_fmt(s.get('cnn'), '.1f')} | "
            f"{_fmt(s.get('sample'), '.1f')} | {_fmt(s.get('mlp'), '.1f')} | {_fmt(r.get('fps'))} |")
    lines += [""] + protocol_notes(rows)
    return "\n".join(lines) + "\n"


def pareto_front(cost: Sequence[float], quality: Sequence[float]) -> np.ndarray:
    """Indices of the points no other point beats in both lower cost and higher quality (sorted by cost)."""
    cost, quality = np.asarray(cost, float), np.asarray(quality, float)
    order = np.argsort(cost, kind="stable")
    front, best = [], -np.inf
    for i in order:
        if quality[i] > best:
            front.append(i)
            best = quality[i]
    return np.asarray(front, dtype=int)


def speed_accuracy_chart(rows: Sequence[dict], path: str | Path, title: str, resolution: str = "") -> Path:
    """Foreground PSNR (padded mask box) against milliseconds per frame, one point per row, with the
    Pareto front drawn (official PSNR for rows without a foreground block)."""
    plt = pyplot()

    ms = [sum(r["stage_ms"].values()) for r in rows]
    psnr = [fg(r, "psnr") if fg(r, "psnr") is not None else r["psnr"] for r in rows]
    ylabel = ("foreground PSNR (dB, padded mask box), held-out cameras" if all(fg(r, "psnr") is not None for r in rows)
              else "PSNR (dB, official protocol), held-out cameras")
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    ax.scatter(ms, psnr, color="tab:blue", zorder=3)
    for x, y, r in zip(ms, psnr, rows):
        ax.annotate(str(r.get("name", r.get("model"))), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    front = pareto_front(ms, psnr)
    if len(front) > 1:
        ax.plot(np.asarray(ms)[front], np.asarray(psnr)[front], "--", color="tab:red", label="Pareto front", zorder=2)
        ax.legend(loc="lower right")
    ax.set_xlabel(f"ms per frame (uv + cnn + sample + mlp){', ' + resolution if resolution else ''}, CPU")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)
