"""Automatic capacity choice: train a ladder of model sizes and keep the cheapest one within a PSNR tolerance.

``auto_capacity(train_cfg, AutoCapacityConfig(tolerance_db=0.5))`` trains every candidate with the
same budget (``train_cfg`` with the candidate's ``model_overrides`` merged in), evaluates each on the
validation split (foreground PSNR, per-stage ms per frame, parameters) and chooses

    among the candidates whose foreground PSNR is within ``tolerance_db`` of the best it measured,
    the one with the lowest ms per frame; candidates within ``ms_tie_rel`` of that lowest time
    count as tied and the one with fewest parameters wins (then the faster).

The search is written to ``train_cfg.out/auto_capacity.json`` (every candidate with its numbers or
its error, the rule and the choice); candidate runs live in ``train_cfg.out/candidates/<name>/`` and
``train_cfg.out/chosen`` is a symbolic link to the chosen one (a copy where links are unsupported).
Candidates that fail (an exception, a non-finite PSNR) are recorded and never chosen.

Selection splits (``AutoCapacityConfig.split``), never a test split:

* ``validation`` (default): every candidate holds out the same training cameras
  (``TrainConfig.validation_cameras``, at least ``AutoCapacityConfig.validation_cameras``) and is
  scored on them over the training frames: a novel-view measure that is not the test cameras.
* ``train``: the training images themselves. This measures how well a model fits, not how it
  generalises, so it favours large models.

The test split (``novel_view``, when the shards have test cameras) scores the chosen candidate only,
after the choice (``test`` in the record).

Runs in one process (not under ``torchrun``). ms per frame is measured on the machine at hand; on a
shared CPU, ``ms_tie_rel`` keeps timing noise from deciding between models of similar cost.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import time
import traceback
from pathlib import Path
from typing import Mapping, Sequence

from deliffas.engine.auto_capacity_config import AutoCapacityConfig, Candidate
from deliffas.engine.data_bridge import shard_info
from deliffas.engine.evaluate import EvalConfig, evaluate
from deliffas.engine.train import TrainConfig, train
from deliffas.models.zoo import get_config

__all__ = ["AutoCapacityConfig", "Candidate", "auto_capacity", "default_ladder", "choose"]

logger = logging.getLogger(__name__)

RESULT_FILE = "auto_capacity.json"


def _describe(overrides: Mapping) -> str:
    parts = []
    for key in sorted(overrides):
        value = overrides[key]
        if isinstance(value, Mapping):
            parts.append(key + "-" + "-".join(f"{k}{v}" for k, v in sorted(value.items())))
        else:
            parts.append(f"{key}{value}")
    return "_".join(parts).replace("_channels", "").replace("feature_layer", "fl") or "preset"


def default_ladder(model: str, preset: str) -> list[Candidate]:
    """Capacities from small to large around the preset of ``model``.

    Five rungs, each scaling the MLP width and the U-Net's base/max channels by a factor and
    choosing the MLP depth: (x1/4, depth / 2), (x1/2, depth / 2), (x1/2, depth), (x1, depth) = the
    preset, (x2, depth). Features enter the MLP after the same relative layer as in the preset.
    """
    cfg = get_config(model, preset)
    depth, width, fl = cfg.mlp.depth, cfg.mlp.width, cfg.mlp.feature_layer
    base, top = cfg.unet.base_channels, cfg.unet.max_channels
    ladder = []
    seen = set()
    for factor, d in ((0.25, max(1, depth // 2)), (0.5, max(1, depth // 2)), (0.5, depth), (1.0, depth), (2.0, depth)):
        w = max(4, int(round(width * factor)))
        b = max(1, int(round(base * factor)))
        m = max(b, int(round(top * factor)))
        f = min(d - 1, int(fl * d / depth))
        key = (d, w, b, m, f)
        if key in seen:
            continue
        seen.add(key)
        overrides = {"mlp": {"depth": d, "width": w, "feature_layer": f},
                     "unet": {"base_channels": b, "max_channels": m}}
        ladder.append(Candidate(f"mlp{d}x{w}_unet{b}-{m}", overrides))
    return ladder


def _candidates(train_cfg, ac_cfg: AutoCapacityConfig) -> list[Candidate]:
    if ac_cfg.candidates is None:
        return default_ladder(train_cfg.model, train_cfg.preset)
    out = []
    for c in ac_cfg.candidates:
        out.append(c if isinstance(c, Candidate) else Candidate(_describe(c), dict(c)))
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise ValueError(f"auto_capacity: candidate names must be unique, got {names}")
    if not out:
        raise ValueError("auto_capacity: no candidates")
    return out


def _merge(base: Mapping, extra: Mapping) -> dict:
    merged = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in base.items()}
    for k, v in extra.items():
        if isinstance(v, Mapping) and isinstance(merged.get(k), Mapping):
            merged[k] = {**merged[k], **v}
        else:
            merged[k] = dict(v) if isinstance(v, Mapping) else v
    return merged


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def choose(records: Sequence[Mapping], tolerance_db: float, ms_tie_rel: float = 0.05,
           cost_key: str = "frame_ms", quality_key: str = "psnr") -> tuple[str | None, float | None]:
    """The rule of the module docstring over candidate records (``name``, ``quality_key``, ``cost_key``,
    ``num_parameters``, ``error``); returns (chosen name, best quality), (None, None) when none is usable."""
    ok = [r for r in records if r.get("error") is None and _finite(r.get(quality_key)) and _finite(r.get(cost_key))]
    if not ok:
        return None, None
    best = max(r[quality_key] for r in ok)
    eligible = [r for r in ok if r[quality_key] >= best - tolerance_db]
    cheapest = min(r[cost_key] for r in eligible)
    tied = [r for r in eligible if r[cost_key] <= cheapest * (1 + ms_tie_rel)]
    pick = min(tied, key=lambda r: (r.get("num_parameters") or 0, r[cost_key]))
    return pick["name"], best


def _set_costs(entry: dict, stage_ms: Mapping[str, float]) -> None:
    stage = dict(stage_ms)
    frame_ms = float(sum(stage.values()))
    entry.update(stage_ms=stage, frame_ms=frame_ms,
                 model_ms=float(stage.get("cnn", 0) + stage.get("sample", 0) + stage.get("mlp", 0)),
                 fps=1000.0 / frame_ms if frame_ms > 0 else None)


def _link_chosen(out: Path, run: Path) -> Path:
    link = out / "chosen"
    if link.is_symlink() or link.is_file():
        link.unlink()
    elif link.is_dir():
        shutil.rmtree(link)
    try:
        link.symlink_to(os.path.relpath(run, out), target_is_directory=True)
    except OSError:  # file systems without symbolic links
        shutil.copytree(run, link)
    return link


def _write_json(path: Path, payload: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=str) + "\n")
    os.replace(tmp, path)


def auto_capacity(train_cfg, ac_cfg: AutoCapacityConfig | None = None) -> dict:
    """Train and evaluate each candidate capacity and choose the cheapest within tolerance.

    Args:
        train_cfg: the ``TrainConfig`` every candidate starts from (its ``out`` holds the search).
        ac_cfg: the search settings (default ``AutoCapacityConfig()``).

    Returns:
        The record written to ``train_cfg.out/auto_capacity.json``: ``{"tolerance_db", "split",
        "iters", "cost", "ms_tie_rel", "timing_repeats", "rule", "candidates": [{"name", "overrides",
        "run", "fg_psnr", "fg_ssim", "flip", "psnr", "ssim", "lpips", "stage_ms", "frame_ms", "model_ms", "fps",
        "num_parameters", "train_s", "error"}], "selection_split", "selection_metric", "validation_cameras",
        "test_cameras", "best_psnr" (best validation foreground PSNR), "choice", "chosen_run", "chosen_link",
        "test" (the chosen candidate on novel_view, or None without test cameras)}``.

    Raises:
        RuntimeError: every candidate failed (the record is written first).
    """
    ac_cfg = ac_cfg or AutoCapacityConfig()
    if train_cfg.time_budget is not None:
        raise ValueError("--auto-capacity trains every candidate the same iterations: give --iters, not "
                         "--time-budget")
    out = Path(train_cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    held_out = train_cfg.validation_cameras or ac_cfg.validation_cameras
    test_cameras = shard_info(train_cfg.shards)["test_cameras"]
    candidates = _candidates(train_cfg, ac_cfg)
    iters = ac_cfg.iters or train_cfg.iters
    record = _new_record(train_cfg, ac_cfg, test_cameras, iters)
    for cand in candidates:
        run = out / "candidates" / cand.name
        overrides = _merge(train_cfg.model_overrides, cand.overrides)
        entry: dict = {"name": cand.name, "overrides": overrides, "run": str(run), "fg_psnr": None, "fg_ssim": None,
                       "flip": None, "psnr": None, "ssim": None, "lpips": None, "stage_ms": None, "frame_ms": None, "model_ms": None, "fps": None,
                       "num_parameters": None, "train_s": None, "error": None}
        t0 = time.perf_counter()
        try:
            cfg = dataclasses.replace(train_cfg, out=str(run), model_overrides=overrides, iters=iters,
                                      checkpoint_every=min(train_cfg.checkpoint_every, iters),
                                      validation_cameras=held_out)
            train(cfg, resume=True)
            record["validation_cameras"] = _recorded_validation_cameras(run)
            entry["train_s"] = time.perf_counter() - t0
            ev = evaluate(EvalConfig(run=str(run), split=ac_cfg.split, max_frames=ac_cfg.max_frames,
                                     device=train_cfg.device))
            fg = ev.foreground
            entry.update(fg_psnr=fg.psnr, fg_ssim=fg.ssim, flip=fg.flip, psnr=ev.official.psnr, ssim=ev.official.ssim,
                         lpips=ev.official.lpips, num_parameters=ev.num_parameters, resolution=list(ev.resolution),
                         images=ev.images)
            _set_costs(entry, ev.stage_ms)
            if not _finite(entry["fg_psnr"]):
                entry["error"] = f"non-finite validation foreground PSNR {entry['fg_psnr']}"
        except Exception as exc:  # a failing capacity is recorded, the search goes on
            logger.warning("auto_capacity: candidate %s failed: %s", cand.name, exc)
            entry["error"] = f"{type(exc).__name__}: {exc}"
            entry["traceback"] = traceback.format_exc(limit=8)
        logger.info("auto_capacity: %s fg PSNR %s, %s ms, %s parameters", cand.name, entry["fg_psnr"], entry["frame_ms"],
                    entry["num_parameters"])
        record["candidates"].append(entry)
        _write_json(out / RESULT_FILE, record)  # progress survives an interruption
    _retime(record["candidates"], ac_cfg, train_cfg.device)
    cost_key = "frame_ms" if ac_cfg.cost == "frame_ms" else "model_ms"
    choice, best = choose(record["candidates"], ac_cfg.tolerance_db, ac_cfg.ms_tie_rel, cost_key, "fg_psnr")
    record["best_psnr"] = best  # foreground PSNR on the selection split
    if choice is None:
        _write_json(out / RESULT_FILE, record)
        raise RuntimeError(f"auto_capacity: every candidate failed; see {out / RESULT_FILE}")
    chosen_run = out / "candidates" / choice
    record.update(choice=choice, chosen_run=str(chosen_run), chosen_link=str(_link_chosen(out, chosen_run)))
    if test_cameras:  # test numbers of the final choice only
        record["test"] = _test_record(chosen_run, choice, ac_cfg, train_cfg.device)
    _write_json(out / RESULT_FILE, record)
    return record


def _new_record(train_cfg: TrainConfig, ac_cfg: AutoCapacityConfig, test_cameras: list, iters: int) -> dict:
    """The search's record before any candidate has run (the keys :func:`auto_capacity` documents)."""
    rule = (f"among candidates with foreground PSNR on the {ac_cfg.split} split >= best - {ac_cfg.tolerance_db} dB, "
            f"the lowest {ac_cfg.cost}; costs within {100 * ac_cfg.ms_tie_rel:g}% of that lowest are ties, decided "
            "by fewest parameters; the test split scores the chosen candidate only")
    return {"model": train_cfg.model, "preset": train_cfg.preset, "shards": str(train_cfg.shards),
            "tolerance_db": ac_cfg.tolerance_db, "split": ac_cfg.split, "selection_split": ac_cfg.split,
            "selection_metric": "fg_psnr (foreground PSNR, padded mask box)", "validation_cameras": None,
            "test_cameras": test_cameras, "iters": iters, "cost": ac_cfg.cost,
            "ms_tie_rel": ac_cfg.ms_tie_rel, "timing_repeats": ac_cfg.timing_repeats, "rule": rule,
            "candidates": [], "best_psnr": None, "choice": None, "chosen_run": None, "chosen_link": None,
            "test": None}


def _retime(candidates: list[dict], ac_cfg: AutoCapacityConfig, device: str) -> None:
    """Re-time round-robin (one frame per candidate per round): load bursts from other processes fall on every
    candidate alike; each stage keeps its minimum."""
    for _ in range(ac_cfg.timing_repeats - 1):
        for entry in candidates:
            if entry["error"] is not None:
                continue
            try:
                again = evaluate(EvalConfig(run=entry["run"], split=ac_cfg.split, max_frames=1, device=device))
            except Exception as exc:  # timing only: keep what was measured
                logger.warning("auto_capacity: re-timing %s failed: %s", entry["name"], exc)
                continue
            _set_costs(entry, {k: min(v, again.stage_ms.get(k, v)) for k, v in entry["stage_ms"].items()})


def _test_record(chosen_run: Path, choice: str, ac_cfg: AutoCapacityConfig, device: str) -> dict:
    """The chosen candidate's numbers on the test split (novel_view)."""
    ev = evaluate(EvalConfig(run=str(chosen_run), split="novel_view", max_frames=ac_cfg.max_frames, device=device))
    return {"split": "novel_view", "candidate": choice, "images": ev.images, "foreground": ev.foreground.to_json(),
            "psnr": ev.official.psnr, "ssim": ev.official.ssim, "metric_protocol": ev.official.protocol}


def _recorded_validation_cameras(run: Path) -> list[int] | None:
    record = json.loads((run / "train_config.json").read_text())
    return record.get("data", {}).get("validation_cameras")
