"""Model configs as JSON-ready dicts and back, and checkpoint directories (safetensors + JSON).

Checkpoint directory layout (no pickle anywhere):

* ``weights.safetensors``: the model's ``state_dict`` (parameters and buffers, contiguous).
* ``config.json``: ``{"format": "deliffas-checkpoint", "version": 1, "config": {...ModelConfig},
  "extra": {...}, "weights_sha256": ..., "weights_bytes": ..., "torch_version": ...}``.

Both are written to temporary names in the same directory and renamed into place (weights
first, config last), so a reader never sees a half-written file; the weights' SHA-256 in the
config detects truncated, corrupted or mismatched weight files (:class:`CheckpointError`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import torch

from deliffas.models.deliffas import DeliffasModel, ModelConfig

__all__ = ["CheckpointError", "Checkpoint", "CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "WEIGHTS_FILE", "CONFIG_FILE",
           "config_to_dict", "config_from_dict", "save_checkpoint", "load_checkpoint"]

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "deliffas-checkpoint"
CHECKPOINT_VERSION = 1
WEIGHTS_FILE = "weights.safetensors"
CONFIG_FILE = "config.json"

T = TypeVar("T")


class CheckpointError(ValueError):
    """A checkpoint directory is missing a file, or a file is truncated, corrupted or inconsistent."""


# ---------------------------------------------------------------------------------------- config <-> dict
def config_to_dict(config: Any) -> dict[str, Any]:
    """A (nested) config dataclass as a JSON-ready dict (tuples become lists in JSON)."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise ValueError(f"config_to_dict: expected a dataclass instance, got {type(config).__name__}")
    return dataclasses.asdict(config)


def _coerce(tp: Any, value: Any, where: str) -> Any:
    if value is None:
        return None
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            if dataclasses.is_dataclass(arg) and isinstance(value, Mapping):
                return config_from_dict(arg, value, where)
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ValueError(f"{where}: expected an object for {tp.__name__}, got {type(value).__name__}")
        return config_from_dict(tp, value, where)
    if origin is tuple and isinstance(value, list):
        return tuple(value)
    return value


def config_from_dict(cls: type[T], data: Mapping[str, Any], where: str = "config") -> T:
    """Rebuild a (nested) config dataclass from :func:`config_to_dict` output.

    Args:
        cls: the dataclass type (e.g. :class:`ModelConfig`).
        data: its dict form.
        where: name used in error messages.

    Raises:
        ValueError: unknown keys or invalid values (naming them).
    """
    if not isinstance(data, Mapping):
        raise ValueError(f"{where}: expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown keys {unknown} for {cls.__name__}")
    kwargs = {k: _coerce(hints[k], v, f"{where}.{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from exc


# ---------------------------------------------------------------------------------------- checkpoints
@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint.

    Attributes:
        model: the model in eval mode on the requested device.
        config: its configuration.
        extra: the JSON ``extra`` dict saved with it (step, metrics, ...).
    """

    model: DeliffasModel
    config: ModelConfig
    extra: dict[str, Any] = field(default_factory=dict)


def _fsync_write(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def save_checkpoint(
    path_dir: str | os.PathLike,
    model: DeliffasModel,
    config: ModelConfig | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``weights.safetensors`` and ``config.json`` into ``path_dir`` (created if needed).

    Args:
        path_dir: checkpoint directory.
        model: the model to save.
        config: its configuration (default ``model.config``; must equal it when given).
        extra: JSON-serialisable metadata (training step, backbone record, ...).

    Returns:
        The directory.

    Raises:
        ValueError: ``config`` differs from ``model.config`` or ``extra`` is not JSON-serialisable.
    """
    from safetensors.torch import save as safetensors_save

    config = model.config if config is None else config
    if config != model.config:
        raise ValueError("save_checkpoint: config differs from model.config")
    extra_dict = dict(extra or {})
    try:
        json.dumps(extra_dict)
    except TypeError as exc:
        raise ValueError(f"save_checkpoint: extra is not JSON-serialisable: {exc}") from exc

    out = Path(path_dir)
    out.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    blob = safetensors_save(state, metadata={"format": CHECKPOINT_FORMAT})
    meta = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": config_to_dict(config),
        "extra": extra_dict,
        "weights_sha256": hashlib.sha256(blob).hexdigest(),
        "weights_bytes": len(blob),
        "torch_version": torch.__version__,
    }
    suffix = f".tmp-{os.getpid()}"
    weights_tmp = out / (WEIGHTS_FILE + suffix)
    config_tmp = out / (CONFIG_FILE + suffix)
    try:
        _fsync_write(weights_tmp, blob)
        os.replace(weights_tmp, out / WEIGHTS_FILE)
        _fsync_write(config_tmp, (json.dumps(meta, indent=2, sort_keys=True) + "\n").encode("utf-8"))
        os.replace(config_tmp, out / CONFIG_FILE)
    finally:
        for tmp in (weights_tmp, config_tmp):
            if tmp.exists():
                tmp.unlink()
    logger.info("saved checkpoint %s (%d tensors, %d bytes)", out, len(state), len(blob))
    return out


def _read_meta(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"{path}: missing (not a deliffas checkpoint directory?)")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{path}: corrupted or truncated JSON ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise CheckpointError(f"{path}: expected format {CHECKPOINT_FORMAT!r}, got {found!r}")
    if meta.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: expected version {CHECKPOINT_VERSION}, got {meta.get('version')!r}")
    for key in ("config", "weights_sha256", "weights_bytes"):
        if key not in meta:
            raise CheckpointError(f"{path}: missing key {key!r}")
    return meta


def load_checkpoint(path_dir: str | os.PathLike, device: str | torch.device = "cpu") -> Checkpoint:
    """Load a checkpoint written by :func:`save_checkpoint` (no pickle, verified by SHA-256).

    Args:
        path_dir: checkpoint directory.
        device: where to put the model.

    Returns:
        The model (eval mode), its config and the ``extra`` dict.

    Raises:
        CheckpointError: a missing, truncated, corrupted or inconsistent file, or weights holding NaN or inf
            (named in the message).
    """
    from safetensors.torch import load as safetensors_load

    root = Path(path_dir)
    config_path, weights_path = root / CONFIG_FILE, root / WEIGHTS_FILE
    meta = _read_meta(config_path)
    try:
        config = config_from_dict(ModelConfig, meta["config"], where=f"{config_path}: config")
    except ValueError as exc:
        raise CheckpointError(str(exc)) from exc
    if not weights_path.is_file():
        raise CheckpointError(f"{weights_path}: missing")
    blob = weights_path.read_bytes()
    if len(blob) != meta["weights_bytes"]:
        raise CheckpointError(
            f"{weights_path}: truncated or wrong file: {config_path.name} records {meta['weights_bytes']} bytes, "
            f"the file has {len(blob)}"
        )
    if hashlib.sha256(blob).hexdigest() != meta["weights_sha256"]:
        raise CheckpointError(f"{weights_path}: corrupted: SHA-256 differs from the one recorded in {config_path.name}")
    try:
        state = safetensors_load(blob)
    except Exception as exc:  # noqa: BLE001 - safetensors raises its own error types
        raise CheckpointError(f"{weights_path}: unreadable safetensors data ({exc})") from exc
    for name, tensor in state.items():  # NaN weights would render corrupted pixels with no error
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{weights_path}: tensor {name!r} holds {int((~torch.isfinite(tensor)).sum())} "
                                  "NaN/inf values (training diverged? resume from an earlier checkpoint)")
    try:
        model = DeliffasModel(config)
    except ValueError as exc:  # a config that parses but describes no buildable model (e.g. atlas side 22)
        raise CheckpointError(f"{config_path}: config: {exc}") from exc
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"{weights_path}: does not match the model of {config_path.name}: {exc}") from exc
    model = model.to(torch.device(device)).eval()
    extra = meta.get("extra") or {}
    logger.info("loaded checkpoint %s (%s, S=%d)", root, config.variant, config.atlas_res)
    return Checkpoint(model=model, config=config, extra=dict(extra))
