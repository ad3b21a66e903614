"""The rays of one camera image the light field shades, found by the open3d ray caster (:class:`CameraRays`).

A pixel is shaded when its ray meets the outer surface (the offset shell encloses the inner
surface, so this is the template silhouette dilated by the offset — DELIFFAS uses a 4-px dilated
silhouette of the same role). Its inner sample is the inner hit, or the outer exit hit where the
ray misses the inner surface (depth peeling, ``uv_inner_or_exit``). Every other pixel is background.
The rasterisers (``fast.rasterize``, ``geometry.rasterize_torch``) give the same rays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import UVRaycaster, uv_inner_or_exit
from deliffas.geometry.shaded_pixels import ShadedPixels
from deliffas.io.cameras import Camera

__all__ = ["CameraRays", "camera_rays", "frame_rays"]


@dataclass(frozen=True)
class CameraRays:
    """The shaded rays of one camera image: numpy arrays from the ray caster, tensors on the model's device from
    the torch rasteriser (every consumer takes either).

    Attributes:
        pixels: (N,) int64 flat pixel index row * W + col of each shaded ray.
        uv_inner: (N, 2) float32, inner hit uv or outer exit uv.
        inner_from_outer: (N,) bool, True where ``uv_inner`` is the outer exit hit.
        uv_outer: (N, 2) float32, first outer hit uv.
        viewdir: (N, 3) float32 unit ray directions, world frame (None from ``fast.uv_sources.device_camera_rays``
            with ``viewdir=False``).
        height, width: image size.
    """

    pixels: np.ndarray | torch.Tensor
    uv_inner: np.ndarray | torch.Tensor
    inner_from_outer: np.ndarray | torch.Tensor
    uv_outer: np.ndarray | torch.Tensor
    viewdir: np.ndarray | torch.Tensor | None
    height: int
    width: int

    @property
    def num_rays(self) -> int:
        return int(self.pixels.shape[0])

    @classmethod
    def from_shaded(cls, shaded: ShadedPixels, camera: Camera) -> "CameraRays":
        """The rays of a rasteriser's shaded pixels of ``camera`` (numpy or tensors, as the rasteriser gave)."""
        return cls(pixels=shaded.pixels, uv_inner=shaded.uv_inner, inner_from_outer=shaded.inner_from_outer,
                   uv_outer=shaded.uv_outer, viewdir=shaded.viewdir, height=camera.height, width=camera.width)


def camera_rays(raycaster: UVRaycaster, camera: Camera, fraction: float = 1.0,
                rng: np.random.Generator | None = None) -> CameraRays:
    """The rays of ``camera`` the light field shades (only the surfaces' projected window is cast); with
    ``fraction`` < 1 a uniform random subset of them, each kept with that probability (drawn by ``rng``)."""
    hits = raycaster.cast_foreground(camera, exits="inner_miss", fraction=fraction, rng=rng)
    uv_in, from_outer = uv_inner_or_exit(hits)
    keep = np.flatnonzero(hits.outer_hit & np.isfinite(uv_in).all(-1) & np.isfinite(hits.uv_outer).all(-1))
    pixels = hits.pixels[keep]  # (N, 2) (col, row)
    _, dirs = camera.rays(pixels + 0.5)
    return CameraRays(
        pixels=pixels[:, 1] * camera.width + pixels[:, 0],
        uv_inner=uv_in[keep].astype(np.float32),
        inner_from_outer=from_outer[keep],
        uv_outer=hits.uv_outer[keep].astype(np.float32),
        viewdir=dirs.astype(np.float32),
        height=camera.height,
        width=camera.width,
    )


def frame_rays(inner_verts: np.ndarray, outer_verts: np.ndarray, faces: np.ndarray, atlas: UVAtlas,
               cameras: Sequence[Camera], fraction: float = 1.0,
               rng: np.random.Generator | None = None) -> list[CameraRays]:
    """Ray sets of several cameras of one frame (the ray-casting scenes are built once); ``fraction`` and
    ``rng`` as :func:`camera_rays`."""
    raycaster = UVRaycaster(np.asarray(inner_verts, np.float32), faces, np.asarray(outer_verts, np.float32), atlas)
    return [camera_rays(raycaster, cam, fraction, rng) for cam in cameras]
