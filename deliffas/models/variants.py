"""The registry of model variants: what each one's U-Nets and light-field MLP take and read.

A variant is a :class:`VariantSpec`, registered by name (:func:`register_variant`; installed packages add
theirs through the ``deliffas.variants`` entry-point group, loaded on the first lookup). The model
(:class:`deliffas.models.deliffas.DeliffasModel`) builds its U-Nets and its MLP's input width from
the spec, and the engine builds each ray's inputs (:class:`deliffas.models.ray_query.RayQuery`)
from it; neither compares variant names. ``ModelConfig.variant`` stays the name, so configs,
checkpoints and run records keep a plain string.

The paper's four (section 4.4 and appendix):

=============================  =====  =========  =======  ===============  =======
name                           outer  inner      viewdir  encoded uvs      peeling
                               U-Net  U-Nets
=============================  =====  =========  =======  ===============  =======
``single_surface``             no     1          no       inner            no
``single_surface_viewdir``     no     1          yes      inner            no
``single_surface_two_unet``    no     2          no       inner            no
``two_surface`` (DELIFFAS)     yes    1          no       outer, inner     yes
=============================  =====  =========  =======  ===============  =======

deliffas's own (:data:`EXTENSION_VARIANTS`):

=============================  =====  =========  =========  ===============  =======
name                           outer  inner      viewdir    encoded uvs      peeling
                               U-Net  U-Nets
=============================  =====  =========  =========  ===============  =======
``two_surface_reflect``        yes    1          reflected  outer, inner     yes
=============================  =====  =========  =========  ===============  =======

``two_surface_reflect`` is DELIFFAS whose MLP also gets the view direction reflected about the posed inner
surface's normal (Ref-NeRF's reflected direction, r = d - 2 (d . n) n): with the light fixed in the world,
a specular highlight is a function of r, which the normal maps alone cannot give (docs/results.md, "What
limits the held-out score").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from deliffas.plugins import load_plugins

__all__ = ["VariantSpec", "register_variant", "unregister_variant", "get_variant", "variant_names", "PAPER_VARIANTS",
           "EXTENSION_VARIANTS", "VARIANTS_ENTRY_POINT"]

VARIANTS_ENTRY_POINT = "deliffas.variants"
"""The entry-point group whose modules register model variants when imported (installed plug-ins)."""

Surface = Literal["outer", "inner"]


@dataclass(frozen=True)
class VariantSpec:
    """What one model variant is made of; the MLP's inputs follow from it.

    The MLP's encoded input is ``PE(uv)`` for each of ``encoded_uvs`` in that order, then
    ``PE(viewdir)`` when ``viewdir`` (of the reflected direction when ``reflect_viewdir``); its feature
    input is the outer map sampled at ``uv_outer`` (when ``outer_unet``) followed by the inner map(s)
    sampled at ``uv_inner``.
    """

    name: str
    """Registry key and the value of ``ModelConfig.variant``."""
    outer_unet: bool = False
    """A U-Net on the outer surface's normal maps, sampled at ``uv_outer`` (needs outer normal maps)."""
    inner_unets: int = 1
    """U-Nets on the inner surface's normal maps (their C-channel maps are concatenated: C_inner = n C)."""
    viewdir: bool = False
    """Whether the MLP gets the encoded unit view direction of each ray."""
    reflect_viewdir: bool = False
    """The encoded direction is the view direction d reflected about the posed inner surface's unit normal n:
    r = d - 2 (d . n) n, with n sampled bilinearly at ``uv_inner`` from the current frame's inner normal map
    (its first three channels; :attr:`FrameFeatures.normals`). Needs ``viewdir``."""
    encoded_uvs: tuple[Surface, ...] = ("inner",)
    """Which hit uvs are positionally encoded into the MLP's input, in this order."""
    inner_from_outer: bool = False
    """Depth peeling: rays that miss the inner surface read their "inner" feature from the outer map
    at the outer exit uv. Needs ``outer_unet`` and one inner U-Net (the two maps then have equal
    channels)."""

    def __post_init__(self) -> None:
        where = f"VariantSpec {self.name!r}"
        if not self.name or not isinstance(self.name, str):
            raise ValueError(f"VariantSpec: name must be a non-empty string, got {self.name!r}")
        if self.inner_unets < 1:
            raise ValueError(f"{where}: inner_unets must be >= 1, got {self.inner_unets}")
        if not self.encoded_uvs and not self.viewdir:
            raise ValueError(f"{where}: the MLP needs an encoded input (encoded_uvs or viewdir)")
        bad = [s for s in self.encoded_uvs if s not in ("outer", "inner")]
        if bad or len(set(self.encoded_uvs)) != len(self.encoded_uvs):
            raise ValueError(f"{where}: encoded_uvs must be distinct 'outer'/'inner', got {self.encoded_uvs}")
        if self.reflect_viewdir and not self.viewdir:
            raise ValueError(f"{where}: reflect_viewdir needs viewdir")
        if self.inner_from_outer and not (self.outer_unet and self.inner_unets == 1):
            raise ValueError(f"{where}: inner_from_outer needs outer_unet and inner_unets == 1")

    @property
    def uses_uv_outer(self) -> bool:
        """Whether rays need their outer first-hit uv (sampled or encoded)."""
        return self.outer_unet or "outer" in self.encoded_uvs

    def feature_dim(self, channels: int) -> int:
        """Width of the sampled features given C channels per U-Net map."""
        return channels * (self.inner_unets + int(self.outer_unet))

    def encoded_dim(self, uv_dim: int, viewdir_dim: int) -> int:
        """Width of the encoded input given the widths of one encoded uv and of the encoded view direction."""
        return uv_dim * len(self.encoded_uvs) + (viewdir_dim if self.viewdir else 0)


PAPER_VARIANTS: tuple[VariantSpec, ...] = (
    VariantSpec("single_surface"),
    VariantSpec("single_surface_viewdir", viewdir=True),
    VariantSpec("single_surface_two_unet", inner_unets=2),
    VariantSpec("two_surface", outer_unet=True, encoded_uvs=("outer", "inner"), inner_from_outer=True),
)
"""The paper's DELIFFAS (``two_surface``) and its three ablations, registered at import."""

EXTENSION_VARIANTS: tuple[VariantSpec, ...] = (
    VariantSpec("two_surface_reflect", outer_unet=True, encoded_uvs=("outer", "inner"), inner_from_outer=True,
                viewdir=True, reflect_viewdir=True),
)
"""Variants beyond the paper's, registered at import: ``two_surface_reflect`` (module docstring)."""

_REGISTRY: dict[str, VariantSpec] = {}


def register_variant(spec: VariantSpec) -> VariantSpec:
    """Add ``spec`` to the registry under ``spec.name``; returns it.

    Raises:
        ValueError: a variant of that name is already registered.
    """
    if not isinstance(spec, VariantSpec):
        raise ValueError(f"register_variant: expected a VariantSpec, got {type(spec).__name__}")
    if spec.name in _REGISTRY:
        raise ValueError(f"register_variant: variant {spec.name!r} is already registered")
    _REGISTRY[spec.name] = spec
    return spec


def unregister_variant(name: str) -> None:
    """Remove a registered variant (for plug-ins and tests that register their own).

    Raises:
        ValueError: no variant of that name is registered.
    """
    get_variant(name)
    del _REGISTRY[name]


def get_variant(name: str) -> VariantSpec:
    """The registered spec of ``name``.

    Raises:
        ValueError: unknown name (the message lists the registered ones).
    """
    load_plugins(VARIANTS_ENTRY_POINT)
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown model variant {name!r}; registered: {', '.join(variant_names())}") from None


def variant_names() -> tuple[str, ...]:
    """Names of the registered variants, in registration order."""
    load_plugins(VARIANTS_ENTRY_POINT)
    return tuple(_REGISTRY)


for _spec in (*PAPER_VARIANTS, *EXTENSION_VARIANTS):
    register_variant(_spec)
