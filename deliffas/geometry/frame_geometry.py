"""Per-frame geometry of the model's inputs: posed inner surface, offset outer surface, normal maps.

One function (``FrameGeometryBuilder.build``) turns pose parameters (or tracked meshes) into what
DELIFFAS consumes per frame, so conversion to shards and free-viewpoint rendering compute exactly
the same thing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float, Integer, Real
from torch import Tensor

from deliffas.checks import check_finite, check_shape
from deliffas.geometry.arrays import ArrayLike, to_torch
from deliffas.geometry.atlas import TexelTable
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.normal_maps import NormalMapGather, temporal_window
from deliffas.geometry.shell import offset_shell

__all__ = ["FrameGeometry", "FrameGeometryBuilder"]


@dataclass(frozen=True)
class FrameGeometry:
    """Geometry of B frames.

    numpy vertices (what shards store) beside torch normal maps (what the model reads).

    Attributes:
        inner: (B, V, 3) float32 numpy, mm, world frame, posed template (inner surface).
        outer: (B, V, 3) float32 numpy, mm, world frame, offset shell (outer surface).
        normal_maps_inner: (B, 3, S, S) tensor of the builder's dtype, world-space unit normals per
            texel in [-1, 1] (0 off the atlas).
        normal_maps_outer: (B, 3, S, S), the same for the outer surface.
    """

    inner: Float[np.ndarray, "B V 3"]
    outer: Float[np.ndarray, "B V 3"]
    normal_maps_inner: Float[Tensor, "B 3 S S"]
    normal_maps_outer: Float[Tensor, "B 3 S S"]

    def window(self, index: int, T: int) -> tuple[Float[Tensor, "C S S"], Float[Tensor, "C S S"]]:
        """Temporal normal maps (3 (T + 1), S, S) of frame ``index``: frames index, index-1, …, clamped at 0."""
        idx = torch.tensor([index])
        return (temporal_window(self.normal_maps_inner, idx, T)[0], temporal_window(self.normal_maps_outer, idx, T)[0])


class FrameGeometryBuilder:
    """Builds ``FrameGeometry`` from posed vertices with fixed per-vertex offsets and a texel table.

    Args:
        faces: (F, 3) template faces.
        offsets_mm: (V,) per-vertex offset d of the outer surface (a constant array = plain shell).
        table: texel table of the template's atlas at side S.
        dtype: dtype of the normal maps (float16 for storage, float32 for the model).
    """

    def __init__(self, faces: Integer[ArrayLike, "F 3"], offsets_mm: Real[ArrayLike, "V"], table: TexelTable,
                 dtype: torch.dtype = torch.float32):
        self.faces = np.asarray(faces, np.int64)
        self.offsets = np.asarray(offsets_mm, np.float64)
        check_shape("offsets_mm", self.offsets, "V")
        self.gather = NormalMapGather.from_table(table, self.faces)
        self.dtype = dtype

    def build(self, inner: Real[ArrayLike, "B V 3"]) -> FrameGeometry:
        """Outer surface and normal maps of posed inner surfaces ``inner`` (B, V, 3) mm."""
        check_shape("inner", inner, "B V 3", {"V": len(self.offsets)})
        check_finite("inner", inner)  # NaN vertices would become NaN normal maps in the shards
        inner = np.asarray(inner, np.float64)
        outer = offset_shell(inner, self.faces, self.offsets)
        nm_in = self.gather.apply(to_torch(vertex_normals(inner, self.faces)), dtype=self.dtype)
        nm_out = self.gather.apply(to_torch(vertex_normals(outer, self.faces)), dtype=self.dtype)
        return FrameGeometry(inner.astype(np.float32), np.asarray(outer, np.float32), nm_in, nm_out)
