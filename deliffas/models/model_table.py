"""The named model configurations deliffas ships, as two tables: one row per size preset, one row per model.

:mod:`deliffas.models.zoo` builds every ``ModelConfig`` from these rows, ``deliffas train`` takes its default
model from :data:`DEFAULT_MODEL`, and the tables of docs/models.md are :func:`preset_table_markdown` and
:func:`model_table_markdown` (a test keeps them equal). Plain data: importing this module imports no torch, so
the command line reads it while parsing.

Every preset uses ``norm="affine"`` in its U-Nets: the original's Keras BatchNorm ran on its (never updated)
moving statistics, i.e. a learned affine map, and one frame per step makes batch statistics differ between
training and rendering (formats doc 3.5).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PresetRow", "ModelRow", "PRESET_ROWS", "MODEL_ROWS", "DEFAULT_MODEL", "DEFAULT_PRESET", "preset_row",
           "model_row", "preset_table_markdown", "model_table_markdown"]


@dataclass(frozen=True)
class PresetRow:
    """A size preset: the atlas, the U-Nets' widths and the light-field MLP."""

    name: str
    atlas_res: int
    """Side S of the atlas (normal maps and feature maps); training replaces it with the shards' side."""
    feature_channels: int
    """Feature channels per map (the U-Nets' output)."""
    unet_base_channels: int
    unet_max_channels: int
    mlp_depth: int
    mlp_width: int
    mlp_feature_layer: int
    """Hidden layer that receives the sampled features."""
    pe_freqs: int
    """Positional-encoding frequencies of the uvs."""
    viewdir_pe_freqs: int
    """Positional-encoding frequencies of the view direction (variants that read one)."""
    use: str
    """What the preset is for (docs)."""


@dataclass(frozen=True)
class ModelRow:
    """A named model: a variant, optionally with texture atlases, at every preset of :data:`PRESET_ROWS`."""

    name: str
    variant: str
    """The variant (``deliffas.models.variants``) it builds."""
    texture: bool = False
    """Learnable texture atlases: ``TEXTURE_CHANNELS`` channels per map at ``TEXTURE_SCALE`` x the atlas side."""
    unet_levels: tuple[tuple[str, int], ...] = ()
    """(preset, U-Net levels) where its U-Nets stop before 1 x 1 maps; other presets: log2 S levels."""
    summary: str = ""
    """What it is (docs)."""

    def levels(self, preset: str) -> int | None:
        """Its U-Nets' levels at ``preset`` (None: log2 S)."""
        return dict(self.unet_levels).get(preset)


TEXTURE_CHANNELS, TEXTURE_SCALE = 8, 1
"""Texture atlases of the textured models: channels per map and side as a multiple of the atlas side (twice the
side fits finer detail but doubles a training step)."""

PRESET_ROWS: tuple[PresetRow, ...] = (
    PresetRow("paper", 1024, 32, 16, 512, 8, 256, 4, 10, 4, "the paper's appendix (GPU)"),
    PresetRow("small", 128, 16, 8, 64, 4, 64, 2, 10, 4, "the default: trains in minutes on 2 CPU cores"),
    PresetRow("realtime", 128, 16, 8, 32, 3, 32, 1, 10, 4,
              "small with under a third of its per-ray MLP work and U-Nets half as wide, for CPU rendering at "
              "940 x 1285 (docs/performance.md)"),
    PresetRow("tiny", 32, 8, 4, 16, 2, 32, 0, 4, 2, "tests"),
)

MODEL_ROWS: tuple[ModelRow, ...] = (
    ModelRow("single_surface", "single_surface", summary="one U-Net on the inner surface's normal map, its uvs "
                                                         "encoded (the paper's single-surface ablation)"),
    ModelRow("single_surface_viewdir", "single_surface_viewdir", summary="single_surface with the view direction"),
    ModelRow("single_surface_two_unet", "single_surface_two_unet",
             summary="single_surface with a second U-Net on the outer surface, one surface sampled"),
    ModelRow("two_surface", "two_surface", summary="DELIFFAS: the inner and outer surfaces' uvs and features "
                                                   "(the paper's model)"),
    ModelRow("two_surface_reflect", "two_surface_reflect",
             summary="two_surface with the view direction reflected about the posed surface normal"),
    ModelRow("two_surface_texture", "two_surface", texture=True,
             summary="two_surface with texture atlases, which hold the appearance normal maps cannot predict"),
    ModelRow("two_surface_reflect_texture", "two_surface_reflect", texture=True, unet_levels=(("small", 4),),
             summary="two_surface_reflect with texture atlases; at small its U-Nets stop at S / 16 maps (the "
                     "default of deliffas train)"),
)

DEFAULT_MODEL = "two_surface_reflect_texture"
"""The model ``deliffas train`` trains by default (docs/results.md, "Time to quality")."""
DEFAULT_PRESET = "small"
"""The preset ``deliffas train`` trains by default."""


def preset_row(name: str) -> PresetRow:
    """The row of preset ``name`` (KeyError listing the presets)."""
    for row in PRESET_ROWS:
        if row.name == name:
            return row
    raise KeyError(f"unknown preset {name!r}; presets: {[r.name for r in PRESET_ROWS]}")


def model_row(name: str) -> ModelRow:
    """The row of model ``name`` (KeyError listing the models of the table)."""
    for row in MODEL_ROWS:
        if row.name == name:
            return row
    raise KeyError(f"unknown model {name!r}; models: {[r.name for r in MODEL_ROWS]}")


def preset_table_markdown() -> str:
    """docs/models.md's preset table."""
    lines = ["| preset | S | U-Net channels (base -> max) | MLP depth x width, features at | features per map | "
             "PE frequencies (uv, direction) | for |", "|---|---:|---|---|---:|---|---|"]
    for r in PRESET_ROWS:
        lines.append(f"| `{r.name}` | {r.atlas_res} | {r.unet_base_channels} -> {r.unet_max_channels} | "
                     f"{r.mlp_depth} x {r.mlp_width}, layer {r.mlp_feature_layer} | {r.feature_channels} | "
                     f"{r.pe_freqs}, {r.viewdir_pe_freqs} | {r.use} |")
    return "\n".join(lines)


def model_table_markdown() -> str:
    """docs/models.md's model table."""
    lines = ["| model | variant | texture atlases | U-Net levels | what it is |", "|---|---|---|---|---|"]
    for r in MODEL_ROWS:
        levels = ", ".join(f"{n} at {p}" for p, n in r.unet_levels) or "log2 S"
        name = f"`{r.name}`" + (" (default)" if r.name == DEFAULT_MODEL else "")
        texture = f"{TEXTURE_CHANNELS} channels" if r.texture else "-"
        lines.append(f"| {name} | `{r.variant}` | {texture} | {levels} | {r.summary} |")
    return "\n".join(lines)
