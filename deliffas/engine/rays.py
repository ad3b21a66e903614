"""Per-camera ray sets of one frame: which pixels the light field shades and with which uvs.

The engine's one way from rays to the model and back: :func:`ray_query` turns a :class:`RayBatch`
into the model's :class:`~deliffas.models.ray_query.RayQuery` for a variant's spec, and
:func:`paint_images` writes the shaded colours into images (train, evaluate and render use both).

A pixel is shaded when its ray meets the outer surface (the offset shell encloses the inner
surface, so this is the template silhouette dilated by the offset — DELIFFAS uses a 4-px dilated
silhouette of the same role). Its inner sample is the inner hit, or the outer exit hit where the
ray misses the inner surface (depth peeling, ``uv_inner_or_exit``). Every other pixel is background.

Two sources give the same rays (up to pixel centres within round-off of a triangle edge): the open3d ray
caster (:func:`camera_rays`, numpy, in the DataLoader workers during training) and the torch rasteriser
(:func:`torch_camera_rays`, tensors on the model's device, in the main process). :func:`uv_source` picks
one: ``auto`` = the torch rasteriser when the device is CUDA, the ray caster on the CPU.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np
import torch

from deliffas.checks import check_shape
from deliffas.engine.config_fields import UV_SOURCES, UVSource, check_uv_source
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.rasterize_torch import TorchUVRasterizer
from deliffas.geometry.raycast import UVRaycaster, uv_inner_or_exit
from deliffas.io.cameras import Camera
from deliffas.models.ray_query import RayQuery
from deliffas.models.variants import VariantSpec

__all__ = ["CameraRays", "camera_rays", "frame_rays", "RayBatch", "stack_rays", "ray_query", "paint_images",
           "UVSource", "UV_SOURCES", "uv_source", "torch_camera_rays", "torch_frame_rays", "device_camera_rays"]


@dataclass(frozen=True)
class CameraRays:
    """The shaded rays of one camera image: numpy arrays from the ray caster, tensors on the model's device from
    the torch rasteriser (every consumer takes either).

    Attributes:
        pixels: (N,) int64 flat pixel index row * W + col of each shaded ray.
        uv_inner: (N, 2) float32, inner hit uv or outer exit uv.
        inner_from_outer: (N,) bool, True where ``uv_inner`` is the outer exit hit.
        uv_outer: (N, 2) float32, first outer hit uv.
        viewdir: (N, 3) float32 unit ray directions, world frame (None from ``engine.realtime.fast_camera_rays``
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


def camera_rays(raycaster: UVRaycaster, camera: Camera) -> CameraRays:
    """The rays of ``camera`` the light field shades (only the surfaces' projected window is cast)."""
    hits = raycaster.cast_foreground(camera, exits="inner_miss")
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
               cameras: Sequence[Camera]) -> list[CameraRays]:
    """Ray sets of several cameras of one frame (the ray-casting scenes are built once)."""
    raycaster = UVRaycaster(np.asarray(inner_verts, np.float32), faces, np.asarray(outer_verts, np.float32), atlas)
    return [camera_rays(raycaster, cam) for cam in cameras]


def uv_source(device: torch.device | str, requested: str = "auto") -> Literal["raycast", "torch"]:
    """The resolved uv source for a model on ``device`` (``UV_SOURCES``; ValueError naming the choices)."""
    check_uv_source(requested)
    if requested == "auto":
        return "torch" if torch.device(device).type == "cuda" else "raycast"
    return requested  # type: ignore[return-value]


def torch_camera_rays(rasterizer: TorchUVRasterizer, camera: Camera, viewdir: bool = True,
                      fallback: UVRaycaster | None = None) -> CameraRays:
    """``camera_rays`` by the torch rasteriser: tensors on its device. Where a vertex is behind the camera the
    rasteriser cannot project: the ray caster ``fallback`` casts then (built from the rasteriser's surfaces when
    None; needs open3d)."""
    got = rasterizer.shaded_pixels(camera, viewdir)
    if got is None:
        raycaster = fallback or UVRaycaster(rasterizer.inner.cpu().numpy(), rasterizer.faces.cpu().numpy(),
                                            rasterizer.outer.cpu().numpy(), rasterizer.atlas)
        rays = camera_rays(raycaster, camera)
        as_t = lambda a: torch.from_numpy(a).to(rasterizer.device)  # noqa: E731
        return CameraRays(as_t(rays.pixels), as_t(rays.uv_inner), as_t(rays.inner_from_outer), as_t(rays.uv_outer),
                          as_t(rays.viewdir) if viewdir else None, camera.height, camera.width)
    return CameraRays(pixels=got.pixels, uv_inner=got.uv_inner, inner_from_outer=got.inner_from_outer,
                      uv_outer=got.uv_outer, viewdir=got.viewdir, height=camera.height, width=camera.width)


def torch_frame_rays(inner_verts: np.ndarray, outer_verts: np.ndarray, faces: np.ndarray, atlas: UVAtlas,
                     cameras: Sequence[Camera], device: torch.device | str) -> list[CameraRays]:
    """``frame_rays`` by the torch rasteriser on ``device`` (the surfaces as ``frame_rays`` casts them: float32)."""
    rasterizer = TorchUVRasterizer(np.asarray(inner_verts, np.float32), faces, np.asarray(outer_verts, np.float32),
                                   atlas, device)
    return [torch_camera_rays(rasterizer, cam) for cam in cameras]


# one torch rasteriser per frame geometry (its ray caster) and device, alive as long as the ray caster
_TORCH_RASTERIZERS: "weakref.WeakKeyDictionary[UVRaycaster, dict[torch.device, TorchUVRasterizer]]" = \
    weakref.WeakKeyDictionary()


def device_camera_rays(raycaster: UVRaycaster, camera: Camera, device: torch.device | str, uv: str = "auto",
                       viewdir: bool = True) -> CameraRays:
    """The shaded rays of ``camera`` from ``uv_source(device, uv)``: the ray caster's (numpy), or the torch
    rasteriser's of the same frame on ``device`` (tensors; built once per ray caster and device)."""
    device = torch.device(device)
    if uv_source(device, uv) == "raycast":
        return camera_rays(raycaster, camera)
    per_device = _TORCH_RASTERIZERS.setdefault(raycaster, {})
    if device not in per_device:
        per_device[device] = TorchUVRasterizer(raycaster.inner_verts, raycaster.faces, raycaster.outer_verts,
                                               raycaster.atlas, device)
    return torch_camera_rays(per_device[device], camera, viewdir, fallback=raycaster)


@dataclass(frozen=True)
class RayBatch:
    """The rays of several cameras (and frames) flattened for one ``DeliffasModel.shade`` call.

    Attributes:
        batch_index: (N,) long, the frame (row of the FrameFeatures batch) of each ray.
        image_index: (N,) long, the image (frame, camera) of each ray, into the stacked images.
        pixels: (N,) long flat pixel index in its image.
        uv_inner, uv_outer: (N, 2) float.
        inner_from_outer: (N,) bool.
        viewdir: (N, 3) float (None from the fast path for variants without a view direction).
    """

    batch_index: torch.Tensor
    image_index: torch.Tensor
    pixels: torch.Tensor
    uv_inner: torch.Tensor
    uv_outer: torch.Tensor
    inner_from_outer: torch.Tensor
    viewdir: torch.Tensor | None

    def to(self, device: torch.device | str) -> "RayBatch":
        return RayBatch(*(getattr(self, f).to(device) for f in self.__dataclass_fields__))

    @property
    def num_rays(self) -> int:
        return int(self.pixels.shape[0])


def stack_rays(rays: Sequence[CameraRays], frame_of_image: Sequence[int]) -> RayBatch:
    """Flatten per-image ray sets; ``frame_of_image[i]`` is the feature batch row of image i."""
    counts = [r.num_rays for r in rays]
    cat = lambda name: torch.cat([torch.as_tensor(getattr(r, name)) for r in rays])  # noqa: E731
    pixels = cat("pixels")
    dev = pixels.device  # the rays' device: the torch rasteriser's rays stay where they were made
    per_image = torch.as_tensor(counts, device=dev)
    return RayBatch(
        batch_index=torch.repeat_interleave(torch.as_tensor(list(frame_of_image), dtype=torch.long, device=dev),
                                            per_image),
        image_index=torch.repeat_interleave(torch.arange(len(rays), device=dev), per_image),
        pixels=pixels,
        uv_inner=cat("uv_inner"),
        uv_outer=cat("uv_outer"),
        inner_from_outer=cat("inner_from_outer"),
        viewdir=cat("viewdir"),
    )


def ray_query(batch: RayBatch, spec: VariantSpec) -> RayQuery:
    """The model's inputs for ``batch``: the per-ray fields ``spec`` reads, None for the others."""
    return RayQuery(
        batch_index=batch.batch_index,
        uv_inner=batch.uv_inner,
        uv_outer=batch.uv_outer if spec.uses_uv_outer else None,
        viewdir=batch.viewdir if spec.viewdir else None,
        inner_from_outer=batch.inner_from_outer if spec.inner_from_outer else None,
    )


def paint_images(colors: torch.Tensor, batch: RayBatch, num_images: int, height: int, width: int,
                 background: float = 0.0) -> torch.Tensor:
    """Images (num_images, H, W, 3) with each ray's colour at its pixel and ``background`` elsewhere.

    Args:
        colors: (N, 3) shaded colours of ``batch``'s rays (differentiable: the result is built
            out of place, so gradients reach ``colors``).
        batch: the rays (their ``image_index`` and flat ``pixels``).
        num_images: number of images of the canvas.
        height: the canvas height, pixels.
        width: the canvas width, pixels.
        background: value of the pixels no ray paints.
    """
    check_shape("colors", colors, f"{batch.num_rays} 3")
    canvas = colors.new_full((num_images, height * width, 3), background)
    canvas = canvas.index_put((batch.image_index, batch.pixels), colors)
    return canvas.reshape(num_images, height, width, 3)
