"""Named model configurations (variant x preset) and safe checkpoints (safetensors + JSON).

Presets (``get_config(name, preset)``):

========  =====  =========================================  ==============  =========  ====
preset    S      U-Net (levels, base -> max channels)       MLP depth x w   features   PE L
========  =====  =========================================  ==============  =========  ====
paper     1024   log2 S = 10, 16 -> 512 (paper appendix)    8 x 256, @4     32         10
small     128    log2 S = 7, 8 -> 64                        4 x 64, @2      16         10
realtime  128    log2 S = 7, 8 -> 32                        3 x 32, @1      16         10
tiny      32     log2 S = 5, 4 -> 16 (tests)                2 x 32, @0      8          4
========  =====  =========================================  ==============  =========  ====

``realtime`` is ``small`` with under a third of its per-ray MLP work (5.9 k against 19.9 k multiply-adds
per ray) and a U-Net half as wide, for CPU rendering at 940 x 1285 (docs/performance.md, "Real-time on
two cores"). Its 16 feature channels per map (8 until session 7) were chosen on the validation split;
on the recipe capture its foreground PSNR is 0.36 dB below ``small``'s (five seeds,
``python -m recipes.presets``).

for each of the four variants (``single_surface``, ``single_surface_viewdir``,
``single_surface_two_unet``, ``two_surface``) and ``two_surface_reflect``, registered under the variant names,
for ``two_surface_texture`` (``TEXTURED``: ``two_surface`` with texture atlases) and for
``two_surface_reflect_texture`` (``REFLECTED``: ``two_surface_reflect`` with texture atlases, the training
default; at ``small`` its U-Nets have ``DEFAULT_UNET_LEVELS`` = 4 levels).

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

from deliffas.models.deliffas import VARIANTS, DeliffasModel, ModelConfig
from deliffas.models.light_field import LightFieldMLPConfig
from deliffas.models.unet import UNetConfig
from deliffas.models.variants import EXTENSION_VARIANTS

__all__ = [
    "CheckpointError",
    "Checkpoint",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "WEIGHTS_FILE",
    "CONFIG_FILE",
    "register",
    "get_config",
    "list_models",
    "list_presets",
    "config_to_dict",
    "config_from_dict",
    "save_checkpoint",
    "load_checkpoint",
]

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "deliffas-checkpoint"
CHECKPOINT_VERSION = 1
WEIGHTS_FILE = "weights.safetensors"
CONFIG_FILE = "config.json"

T = TypeVar("T")


class CheckpointError(ValueError):
    """A checkpoint directory is missing a file, or a file is truncated, corrupted or inconsistent."""


# ---------------------------------------------------------------------------------------- registry
_REGISTRY: dict[str, dict[str, ModelConfig]] = {}


def register(name: str, presets: Mapping[str, ModelConfig], *, overwrite: bool = False) -> None:
    """Register a named model with its presets.

    Args:
        name: model name (e.g. ``"two_surface"``).
        presets: preset name -> configuration.
        overwrite: replace an existing registration instead of raising.

    Raises:
        ValueError: ``name`` already registered (and not ``overwrite``), or no presets.
    """
    if not presets:
        raise ValueError(f"register: model {name!r} needs at least one preset")
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"register: model {name!r} is already registered (pass overwrite=True to replace)")
    for preset, cfg in presets.items():
        if not isinstance(cfg, ModelConfig):
            raise ValueError(f"register: {name}/{preset}: expected a ModelConfig, got {type(cfg).__name__}")
    _REGISTRY[name] = dict(presets)


def list_models() -> list[str]:
    """Registered model names, sorted."""
    return sorted(_REGISTRY)


def list_presets(name: str) -> list[str]:
    """Preset names of a registered model."""
    if name not in _REGISTRY:
        raise KeyError(f"unknown model {name!r}; registered: {list_models()}")
    return list(_REGISTRY[name])


def get_config(name: str, preset: str = "small") -> ModelConfig:
    """The configuration of a registered model at a preset.

    Raises:
        KeyError: unknown model or preset (the message lists the known ones).
    """
    if name not in _REGISTRY:
        raise KeyError(f"unknown model {name!r}; registered: {list_models()}")
    presets = _REGISTRY[name]
    if preset not in presets:
        raise KeyError(f"model {name!r} has no preset {preset!r}; presets: {list(presets)}")
    return presets[preset]


def _preset(variant: str, preset: str) -> ModelConfig:
    # All presets use norm="affine": the original's Keras BatchNorm ran on its (never updated) moving
    # statistics, i.e. a learned affine map, and one frame per step makes batch statistics differ
    # between training and rendering (formats doc 3.5).
    if preset == "paper":
        return ModelConfig(variant=variant, atlas_res=1024,  # type: ignore[arg-type]
                           unet=UNetConfig(in_channels=9, out_channels=32, norm="affine"))
    # (atlas side, channels per map, U-Net base / max channels, MLP depth / width / feature layer)
    compact = {"small": (128, 16, 8, 64, 4, 64, 2), "realtime": (128, 16, 8, 32, 3, 32, 1)}
    if preset in compact:
        side, channels, base, top, depth, width, feature_layer = compact[preset]
        return ModelConfig(
            variant=variant,  # type: ignore[arg-type]
            atlas_res=side,
            feature_channels=channels,
            unet=UNetConfig(in_channels=9, out_channels=channels, base_channels=base, max_channels=top, norm="affine"),
            mlp=LightFieldMLPConfig(depth=depth, width=width, feature_layer=feature_layer),
        )
    if preset == "tiny":
        return ModelConfig(
            variant=variant,  # type: ignore[arg-type]
            atlas_res=32,
            feature_channels=8,
            pe_freqs=4,
            viewdir_pe_freqs=2,
            unet=UNetConfig(in_channels=9, out_channels=8, base_channels=4, max_channels=16, norm="affine"),
            mlp=LightFieldMLPConfig(depth=2, width=32, feature_layer=0),
        )
    raise ValueError(f"unknown preset {preset!r}")


PRESETS: tuple[str, ...] = ("paper", "small", "realtime", "tiny")
"""The presets every registered model has."""
for _variant in (*VARIANTS, *(spec.name for spec in EXTENSION_VARIANTS)):
    register(_variant, {p: _preset(_variant, p) for p in PRESETS})

TEXTURED = "two_surface_texture"
"""DELIFFAS with texture atlases (the default of ``deliffas train``): ``two_surface`` plus
``TEXTURE_CHANNELS`` learnable feature channels per map at ``TEXTURE_SCALE`` x the atlas side (twice the side
fits finer detail but doubles a training step), which hold
the appearance that normal maps cannot predict (docs/results.md, "Time to quality")."""
TEXTURE_CHANNELS, TEXTURE_SCALE = 8, 1
REFLECTED = "two_surface_reflect_texture"
"""``two_surface_reflect`` with the texture atlases of ``TEXTURED`` (the default of ``deliffas train``): the view
direction reflected about the posed surface normal gives the MLP the specular highlights a fixed light puts on a
moving body (docs/results.md, "The view direction reflected about the normal")."""
DEFAULT_UNET_LEVELS = 4
"""U-Net levels of ``REFLECTED`` at the ``small`` preset (the default of ``deliffas train``): its maps stop at
S / 16 (16 x 16 at S = 256) instead of 1 x 1. The levels below hold 14 % of the U-Nets' FLOPs but about a sixth
of a CPU training step's time, and the validation camera scores no worse without them (docs/results.md, "The
U-Net's depth")."""


def _textured(variant: str, preset: str, levels: int | None = None) -> ModelConfig:
    config = dataclasses.replace(_preset(variant, preset), texture_channels=TEXTURE_CHANNELS,
                                 texture_scale=TEXTURE_SCALE)
    return config if levels is None else dataclasses.replace(config, unet=dataclasses.replace(config.unet,
                                                                                                levels=levels))


register(TEXTURED, {p: _textured("two_surface", p) for p in PRESETS})
register(REFLECTED, {p: _textured("two_surface_reflect", p, DEFAULT_UNET_LEVELS if p == "small" else None)
                     for p in PRESETS})


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
