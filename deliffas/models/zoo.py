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

Config <-> dict and checkpoint I/O live in :mod:`deliffas.models.checkpoint` (re-exported here).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from deliffas.models.deliffas import VARIANTS, ModelConfig
from deliffas.models.light_field import LightFieldMLPConfig
from deliffas.models.unet import UNetConfig
from deliffas.models.variants import EXTENSION_VARIANTS
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
