"""Several seeds per configuration: train + evaluate each, aggregate mean ± std, test an ordering.

A recipe row is one configuration trained with ``--seeds N`` training seeds (the capture stays the
same). ``train_seeds`` returns the row: the first seed's full evaluation (every key of
``deliffas eval --json``) plus ``seeds``, ``per_seed`` (the compact numbers of every seed) and
``stats`` ({metric: {"mean", "std", "values"}}). Metrics aggregated (``STAT_KEYS``): foreground
PSNR/SSIM/FLIP and masked PSNR on novel views, foreground PSNR on novel poses and on the training
cameras (the fit), and the official PSNR. ``ordering`` decides whether ``a >= b + target`` holds,
by how much, in how many seeds, and whether the difference is within the seeds' noise.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

__all__ = ["STAT_KEYS", "STAT_LABELS", "compact", "aggregate", "mean", "Ordering", "ordering", "format_stat",
           "stats_table", "default_seeds", "train_seeds"]

STAT_KEYS = ("fg_psnr", "fg_ssim", "fg_flip", "masked_psnr", "pose_fg_psnr", "train_fg_psnr", "psnr")
STAT_LABELS = {"fg_psnr": "fg PSNR ↑ (novel view)", "fg_ssim": "fg SSIM ↑", "fg_flip": "fg FLIP ↓",
               "masked_psnr": "masked PSNR ↑", "pose_fg_psnr": "fg PSNR ↑ (novel pose)",
               "train_fg_psnr": "fg PSNR (training cameras, fit)", "psnr": "official PSNR"}


def default_seeds(quick: bool, requested: int | None) -> int:
    """``--seeds``: as requested, else 1 in quick mode and 3 in full mode."""
    n = requested if requested is not None else (1 if quick else 3)
    if n < 1:
        raise SystemExit(f"--seeds must be >= 1, got {n}")
    return n


def compact(novel_view: dict, novel_pose: dict | None = None, train_fit: dict | None = None) -> dict:
    """The aggregated numbers of one seed from its evaluations (None where not evaluated/available)."""
    fg = novel_view.get("foreground") or {}

    def fgp(ev):
        return None if ev is None else (ev.get("foreground") or {}).get("psnr")

    return {"fg_psnr": fg.get("psnr"), "fg_ssim": fg.get("ssim"), "fg_flip": fg.get("flip"),
            "masked_psnr": fg.get("masked_psnr"), "pose_fg_psnr": fgp(novel_pose), "train_fg_psnr": fgp(train_fit),
            "psnr": novel_view.get("psnr")}


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def aggregate(per_seed: Sequence[dict]) -> dict:
    """{key: {"mean", "std" (sample std, 0 for one seed), "values"}} over the seeds' compact numbers."""
    out = {}
    for key in STAT_KEYS:
        values = [s.get(key) for s in per_seed]
        ok = [v for v in values if _finite(v)]
        out[key] = {"mean": statistics.fmean(ok) if ok else None,
                    "std": statistics.stdev(ok) if len(ok) > 1 else (0.0 if ok else None), "values": values}
    return out


def mean(row: dict, key: str) -> float | None:
    return row["stats"][key]["mean"]


@dataclass(frozen=True)
class Ordering:
    """Whether ``a - b >= target`` (``higher_is_better``) or ``a - b <= -target`` (lower), over seeds."""

    claim: str
    """The claim in words."""
    target: float
    """The margin the claim needs, in the metric's unit."""
    difference: float | None
    """mean(a) - mean(b)."""
    noise: float | None
    """Standard error of that difference from the seeds' standard deviations (None for one seed)."""
    holds: bool | None
    """Whether the mean difference meets the target (None when a number is missing)."""
    seeds_holding: str
    """In how many seeds the paired (same-seed) difference meets the target, e.g. ``2 of 3``."""
    within_noise: bool | None
    """|difference - target| < 2 x noise: the seeds cannot tell whether the claim holds."""

    def sentence(self, unit: str = "dB") -> str:
        if self.holds is None:
            return f"{self.claim}: not measured"
        d = 2 if unit == "dB" else 4
        noise = "" if self.noise is None else f" ± {self.noise:.{d}f} (s.e.)"
        verdict = "HOLDS" if self.holds else "DOES NOT HOLD"
        extra = " — within the seeds' noise, not resolved" if self.within_noise else ""
        unit = f" {unit}" if unit else ""
        return (f"{self.claim}: {verdict} — difference {self.difference:+.{d + 1}f}{noise}{unit} against the target "
                f"{self.target:+.{d + 1}f}{unit}; {self.seeds_holding} seeds{extra}.")

    def to_dict(self) -> dict:
        return {"claim": self.claim, "target": self.target, "difference": self.difference, "noise": self.noise,
                "holds": self.holds, "seeds_holding": self.seeds_holding, "within_noise": self.within_noise}


def ordering(claim: str, a: dict, b: dict, key: str, target: float, higher_is_better: bool = True) -> Ordering:
    """Test ``a`` better than ``b`` by at least ``target`` on ``key`` (rows from ``train_seeds``)."""
    sa, sb = a["stats"][key], b["stats"][key]
    if sa["mean"] is None or sb["mean"] is None:
        return Ordering(claim, target, None, None, None, "0 of 0", None)
    sign = 1.0 if higher_is_better else -1.0
    diff = sa["mean"] - sb["mean"]
    n = min(len([v for v in sa["values"] if _finite(v)]), len([v for v in sb["values"] if _finite(v)]))
    noise = math.sqrt((sa["std"] ** 2 + sb["std"] ** 2) / n) if n > 1 else None
    paired = [(x, y) for x, y in zip(sa["values"], sb["values"]) if _finite(x) and _finite(y)]
    k = sum(1 for x, y in paired if sign * (x - y) >= target)
    holds = bool(sign * diff >= target)
    within = None if noise is None else bool(abs(sign * diff - target) < 2 * noise)
    return Ordering(claim, target, diff, noise, holds, f"{k} of {len(paired)}", within)


def format_stat(stat: dict, spec: str = ".2f") -> str:
    """``mean ± std`` of one ``aggregate`` entry (``n/a`` when no seed has the number)."""
    if stat["mean"] is None:
        return "n/a"
    return f"{stat['mean']:{spec}} ± {stat['std']:{spec}}"


def stats_table(rows: Sequence[dict], keys: Sequence[str] = STAT_KEYS) -> list[str]:
    """Markdown: one line per configuration, mean ± std over its seeds of each metric."""
    spec = {"fg_ssim": ".4f", "fg_flip": ".4f"}
    lines = ["| configuration | seeds | " + " | ".join(STAT_LABELS[k] for k in keys) + " |",
             "|---|---:|" + "---:|" * len(keys)]
    for r in rows:
        lines.append(f"| {r['name']} | {len(r['seeds'])} | "
                     + " | ".join(format_stat(r["stats"][k], spec.get(k, ".2f")) for k in keys) + " |")
    return lines


def train_seeds(name: str, seeds: Sequence[int], run_dir: Path, one_seed: Callable[[int, Path], tuple[dict, dict, dict]]) -> dict:
    """Run ``one_seed(seed, run_dir/seed<seed>) -> (novel_view, novel_pose, train_fit)`` per seed; the row."""
    per_seed, first = [], None
    for seed in seeds:
        nv, np_, fit = one_seed(seed, Path(run_dir) / f"seed{seed}")
        first = first or {**nv, "novel_pose": _brief(np_), "train_fit": _brief(fit)}
        per_seed.append({"seed": seed, "run": nv.get("run"), **compact(nv, np_, fit)})
    row = dict(first)
    row.update(name=name, seeds=list(seeds), per_seed=per_seed, stats=aggregate(per_seed))
    row.update({f"{k}_mean": v["mean"] for k, v in row["stats"].items()})  # flat keys for charts
    return row


def _brief(ev: dict | None) -> dict | None:
    if ev is None:
        return None
    return {k: ev.get(k) for k in ("split", "images", "cameras", "foreground", "psnr", "ssim", "flip", "grid",
                                   "warnings")}
