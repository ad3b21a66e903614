"""What ``train --resume`` continues: the run's own settings, changed only where a change is safe.

A resumed run takes every :class:`TrainConfig` field from its ``train_config.json``. Of the settings
given again, those in :data:`MAY_CHANGE` replace the run's (``iters`` extends it, the shards may have
moved, the device and workers are the machine's); any other one must equal the run's, else a
``ValueError`` names the field and both values.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from deliffas.engine.checkpointing import STATE_FILE, read_training_state
from deliffas.engine.identity import check_run_shards
from deliffas.engine.train_config import TrainConfig

__all__ = ["MAY_CHANGE", "resumed_config", "iterations_done"]

MAY_CHANGE = ("iters", "shards", "out", "device", "num_workers", "checkpoint_every", "preview_every", "log_every",
              "progress", "ray_chunk", "vgg16_path", "uv")
"""The fields a resumed run may change; every other one is the run's."""


def _same(a, b) -> bool:
    norm = (lambda v: tuple(v) if isinstance(v, list) else v)
    return norm(a) == norm(b)


def resumed_config(run: str | os.PathLike, given: dict, names: dict[str, str] | None = None) -> TrainConfig:
    """The config that continues ``run``: its recorded settings, with ``given`` where they may change.

    Args:
        run: the run folder (holds ``train_config.json``).
        given: the fields set explicitly (command-line flags, ``--config``); ``shards`` None = the run's.
        names: how to name a field in a message (a CLI passes its flags, e.g. ``num_workers`` -> ``--workers``).

    Raises:
        ValueError: a given field other than :data:`MAY_CHANGE` differs from the run's (names both values),
            or the run's record is unreadable; FileNotFoundError: the run's shards are gone.
    """
    iterations_done(run)  # a broken training state is named before anything else is read
    path = Path(run) / "train_config.json"
    try:
        record = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: corrupted JSON ({exc})") from None
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    values = {k: v for k, v in record.get("train", {}).items() if k in known}
    values.setdefault("rays_per_step", None)  # recorded before the field existed: every ray was shaded
    # recorded before these existed: the schedule's beta2 (converge / paper: 0.999) and no hold-decay, so that a
    # given value is compared with what the run used (its saved optimizer keeps its own betas)
    values.setdefault("adam_beta2", None)
    values.setdefault("decay_share", TrainConfig.decay_share)
    name = (names or {}).get
    for key, value in given.items():
        if key not in known:
            raise ValueError(f"unknown config key {key!r} (known: {sorted(known)})")
        if value is None or key in MAY_CHANGE:
            continue
        if key in values and not _same(values[key], value):
            raise ValueError(f"{name(key, key)}: the run {run} was trained with {key} {values[key]!r}, not "
                             f"{value!r}; leave {name(key, key)} out to continue it as it was trained (a resumed run "
                             f"may change only {', '.join(name(k, k) for k in MAY_CHANGE if k != 'out')})")
    values.update({k: v for k, v in given.items() if v is not None and k in MAY_CHANGE})
    values["shards"] = str(check_run_shards(run, record, given.get("shards")).out_dir)
    values["out"] = str(run)
    if isinstance(values.get("validation_cameras"), list):
        values["validation_cameras"] = tuple(values["validation_cameras"])
    return TrainConfig(**values)


def iterations_done(run: str | os.PathLike) -> int | None:
    """The iteration the run's last checkpoint holds; None when it has none."""
    return read_training_state(Path(run))["iteration"] if (Path(run) / STATE_FILE).is_file() else None
