"""Named model configurations (model x preset), registered from the tables of :mod:`deliffas.models.model_table`.

``get_config(name, preset)`` returns the ``ModelConfig`` of a registered model at a preset; docs/models.md shows
both tables (models, presets). A plug-in registers more names with :func:`register`.

Config <-> dict and checkpoint I/O live in :mod:`deliffas.models.checkpoint` (re-exported here).
"""

from __future__ import annotations

from collections.abc import Mapping

from deliffas.models.deliffas import ModelConfig
from deliffas.models.light_field import LightFieldMLPConfig
from deliffas.models.unet import UNetConfig
from deliffas.models.model_table import (DEFAULT_MODEL, MODEL_ROWS, PRESET_ROWS, TEXTURE_CHANNELS, TEXTURE_SCALE,
                                         ModelRow, PresetRow, model_row)
from deliffas.models.checkpoint import (CHECKPOINT_FORMAT, CHECKPOINT_VERSION, CONFIG_FILE, WEIGHTS_FILE, Checkpoint,
                                        CheckpointError, config_from_dict, config_to_dict, load_checkpoint,
                                        save_checkpoint)

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


def _config(model: ModelRow, preset: PresetRow) -> ModelConfig:
    """The ``ModelConfig`` of one model at one preset (the tables' rows)."""
    return ModelConfig(
        variant=model.variant,  # type: ignore[arg-type]
        atlas_res=preset.atlas_res,
        feature_channels=preset.feature_channels,
        pe_freqs=preset.pe_freqs,
        viewdir_pe_freqs=preset.viewdir_pe_freqs,
        texture_channels=TEXTURE_CHANNELS if model.texture else 0,
        texture_scale=TEXTURE_SCALE,
        unet=UNetConfig(in_channels=9, out_channels=preset.feature_channels, base_channels=preset.unet_base_channels,
                        max_channels=preset.unet_max_channels, norm="affine", levels=model.levels(preset.name)),
        mlp=LightFieldMLPConfig(depth=preset.mlp_depth, width=preset.mlp_width, feature_layer=preset.mlp_feature_layer),
    )


PRESETS: tuple[str, ...] = tuple(p.name for p in PRESET_ROWS)
"""The presets every registered model has."""
for _row in MODEL_ROWS:
    register(_row.name, {p.name: _config(_row, p) for p in PRESET_ROWS})

TEXTURED = "two_surface_texture"
"""``two_surface`` with texture atlases (``model_table.MODEL_ROWS``)."""
REFLECTED = DEFAULT_MODEL
"""``two_surface_reflect`` with texture atlases: the default of ``deliffas train``."""
DEFAULT_UNET_LEVELS = model_row(REFLECTED).levels("small")
"""U-Net levels of ``REFLECTED`` at the ``small`` preset: its maps stop at S / 16 (16 x 16 at S = 256) instead of
1 x 1; the levels below hold 14 % of the U-Nets' FLOPs but about a sixth of a CPU training step's time, and the
validation camera scores no worse without them (docs/results.md, "The U-Net's depth")."""
