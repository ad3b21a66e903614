"""Per-frame UV-space normal maps as a gather through a precomputed texel table.

Conventions (docs/conventions.md): world-space unit normals, channel-first (3, S, S), values in
[-1, 1] (not (n + 1) / 2), 0 on texels that are not ``valid`` in the texel table. The temporal
window stacks frames f, f-1, ..., f-T along channels (oldest last), clamped at the first frame.

The texel -> (face, barycentrics) table depends only on the atlas, so it is turned once into
per-texel (vertex index, weight) triples; each frame is then one gather and a weighted sum.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np
import torch

from deliffas.checks import check_shape
from deliffas.geometry.atlas import TexelTable, UVAtlas, uv_texel_table

__all__ = [
    "NormalMapGather",
    "normal_maps",
    "temporal_window",
    "rasterize_normal_map_naive",
    "NORMAL_EPS",
]

ArrayLike = Union[np.ndarray, torch.Tensor]

NORMAL_EPS = 1e-8
"""Interpolated normals shorter than this are written as 0 (cannot be normalised)."""


@dataclass(frozen=True)
class NormalMapGather:
    """Per-texel vertex indices and barycentric weights of one atlas at side S.

    Attributes:
        size: S.
        vert_index: (S*S, 3) int64, vertices of the texel's face (0 where the texel is not valid).
        weights: (S*S, 3) float32, barycentrics (0 where the texel is not valid, so the
            interpolated normal is 0 there).
    """

    size: int
    vert_index: torch.Tensor
    weights: torch.Tensor

    @classmethod
    def from_table(cls, table: TexelTable, faces: ArrayLike) -> "NormalMapGather":
        """Flatten a texel table against the mesh's faces.

        Args:
            table: TexelTable of side S (``face``/``bary`` of every texel).
            faces: (F, 3) int, the same faces the atlas was built for.
        """
        check_shape("faces", faces, "F 3")
        faces_np = faces.cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
        face = table.face.reshape(-1)
        if face.max(initial=-1) >= len(faces_np):
            raise ValueError(f"texel table refers to face {face.max()} but faces has {len(faces_np)} rows")
        valid = table.valid.reshape(-1) & (face >= 0)
        vert_index = np.where(valid[:, None], faces_np[np.maximum(face, 0)], 0).astype(np.int64)
        weights = np.where(valid[:, None], table.bary.reshape(-1, 3), 0.0).astype(np.float32)
        return cls(table.size, torch.from_numpy(vert_index), torch.from_numpy(weights))

    def to(self, device: Union[str, torch.device]) -> "NormalMapGather":
        """The same gather with its index and weight tensors on ``device``."""
        return NormalMapGather(self.size, self.vert_index.to(device), self.weights.to(device))

    def apply(self, vertex_normals: ArrayLike, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Normal maps of one or more frames.

        Args:
            vertex_normals: (..., V, 3) float, unit world-space vertex normals (torch or numpy).
            dtype: output dtype (e.g. ``torch.float16`` for storage); default: input dtype.
                Interpolation runs in the input dtype (float32 at least).

        Returns:
            (..., 3, S, S) tensor on the input's device: barycentric interpolation of the three
            vertex normals of each valid texel's face, re-normalised; 0 where not valid.
        """
        check_shape("vertex_normals", vertex_normals, "* V 3")
        vn = vertex_normals if isinstance(vertex_normals, torch.Tensor) else torch.from_numpy(np.asarray(vertex_normals))
        out_dtype = dtype or vn.dtype
        if not vn.dtype.is_floating_point or vn.dtype in (torch.float16, torch.bfloat16):
            vn = vn.float()
        lead = vn.shape[:-2]
        S = self.size
        vi = self.vert_index.to(vn.device)
        w = self.weights.to(device=vn.device, dtype=vn.dtype)
        vt = vn.reshape(-1, vn.shape[-2], 3).transpose(1, 2)  # (B, 3, V)
        gathered = vt[:, :, vi.reshape(-1)].reshape(vt.shape[0], 3, S * S, 3)  # (B, 3, S*S, 3 corners)
        n = (gathered * w).sum(dim=-1)  # (B, 3, S*S)
        length = n.norm(dim=1, keepdim=True)
        n = torch.where(length > NORMAL_EPS, n / length.clamp_min(NORMAL_EPS), torch.zeros_like(n))
        return n.reshape(*lead, 3, S, S).to(out_dtype)


def normal_maps(vertex_normals: ArrayLike, faces: ArrayLike, table: TexelTable, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Normal maps (B, 3, S, S) of vertex normals (B, V, 3) through ``table``.

    One-shot convenience over ``NormalMapGather.from_table(table, faces).apply(...)``; build the
    gather once and reuse it when converting many frames.
    """
    return NormalMapGather.from_table(table, faces).apply(vertex_normals, dtype=dtype)


def temporal_window(maps_per_frame: ArrayLike, frame_indices: ArrayLike, window: int) -> ArrayLike:
    """Stack frames f, f-1, ..., f-T along channels, clamped at the first frame.

    Args:
        maps_per_frame: (F, 3, S, S) normal maps of consecutive frames 0..F-1 (torch or numpy).
        frame_indices: (B,) int, the current frame f of each batch item (index into axis 0).
        window: T, the number of previous frames (T = 2 in DELIFFAS: t, t-1, t-2).

    Returns:
        (B, 3 (T + 1), S, S), same kind as ``maps_per_frame``; channels [3k:3k+3] hold frame
        max(f - k, 0).
    """
    sizes = check_shape("maps_per_frame", maps_per_frame, "F 3 S S")
    check_shape("frame_indices", frame_indices, "B")
    if window < 0:
        raise ValueError(f"temporal_window: window must be >= 0, got {window}")
    if isinstance(maps_per_frame, torch.Tensor):
        fi = torch.as_tensor(frame_indices, device=maps_per_frame.device, dtype=torch.long)
        if fi.numel() and (fi.min() < 0 or fi.max() >= sizes["F"]):
            raise ValueError(f"frame_indices: must be in [0, {sizes['F']}), got [{int(fi.min())}, {int(fi.max())}]")
        idx = (fi[:, None] - torch.arange(window + 1, device=fi.device)).clamp_min(0)  # (B, T+1)
        out = maps_per_frame[idx]  # (B, T+1, 3, S, S)
    else:
        fi = np.asarray(frame_indices, dtype=np.int64)
        if fi.size and (fi.min() < 0 or fi.max() >= sizes["F"]):
            raise ValueError(f"frame_indices: must be in [0, {sizes['F']}), got [{fi.min()}, {fi.max()}]")
        idx = np.maximum(fi[:, None] - np.arange(window + 1), 0)
        out = np.asarray(maps_per_frame)[idx]
    S = sizes["S"]
    return out.reshape(len(fi), 3 * (window + 1), S, S)


def rasterize_normal_map_naive(
    vertex_normals: ArrayLike, faces: ArrayLike, atlas: UVAtlas, size: int, gutter: int = 2
) -> torch.Tensor:
    """Baseline for benchmarks: re-rasterise the atlas for every frame, then interpolate.

    Same result as ``NormalMapGather.apply`` but pays ``uv_texel_table`` per frame, as a
    renderer that draws the normal map in UV space each frame does.

    Args:
        vertex_normals: (B, V, 3) float unit normals.
        faces: (F, 3) int.
        atlas: UVAtlas of the mesh.
        size: S.
        gutter: dilation rings.

    Returns:
        (B, 3, S, S) float tensor.
    """
    check_shape("vertex_normals", vertex_normals, "B V 3")
    vn = vertex_normals if isinstance(vertex_normals, torch.Tensor) else torch.from_numpy(np.asarray(vertex_normals))
    frames = []
    for b in range(vn.shape[0]):  # per frame, by design of this baseline
        table = uv_texel_table(atlas, size, gutter)
        frames.append(NormalMapGather.from_table(table, faces).apply(vn[b]))
    return torch.stack(frames)
