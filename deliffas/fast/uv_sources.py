"""The three uv sources side by side: where a camera's shaded pixels and their inner/outer uvs come from.

=========  ==========================================  ===========  =======================================
source     implementation                              device       where it runs
=========  ==========================================  ===========  =======================================
raster     the C rasteriser (``fast.rasterize``)       CPU (numpy)  data workers in training; the rendering
                                                                    process in eval, render and view
raycast    the open3d ray caster (``geometry.raycast``) CPU (numpy)  as raster; needs open3d
torch      the torch rasteriser                        the model's  the main process (tensors on the device)
           (``geometry.rasterize_torch``)              device
=========  ==========================================  ===========  =======================================

All three give the same rays (up to pixel centres within round-off of a triangle edge); where a vertex is behind
the camera the rasterisers cannot project and the ray caster casts. :func:`uv_source` resolves ``auto``: the C
rasteriser where its kernel builds (a few times faster than the ray caster, and no open3d), except on CUDA for
images above :data:`RASTER_MAX_PIXELS_ON_GPU` made in the rendering process; else the torch rasteriser on CUDA and
the ray caster on the CPU. The choice is ``RenderPathConfig.uv`` (``deliffas.fast.config``; eval, render, view)
and ``TrainConfig.uv``; both render paths take it.
"""

from __future__ import annotations

import weakref
from typing import Literal, Sequence

import numpy as np
import torch

from deliffas.fast.config import check_uv_source
from deliffas.fast.rasterize import raster_kernel_available, rasterized_camera_rays
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.camera_rays import CameraRays, camera_rays
from deliffas.geometry.rasterize_torch import TorchUVRasterizer
from deliffas.geometry.raycast import UVRaycaster
from deliffas.io.cameras import Camera

__all__ = ["RASTER_MAX_PIXELS_ON_GPU", "uv_source", "device_camera_rays", "raster_frame_rays", "torch_camera_rays",
           "torch_frame_rays"]

RASTER_MAX_PIXELS_ON_GPU = 1 << 19
"""Above this many pixels per image, ``uv="auto"`` renders on CUDA with the torch rasteriser: the C one runs on one
CPU core in the rendering process, on the frame's critical path (on an H100, docs/performance.md "GPU": faster
at 256², even at 384²-724², slower at 1024² and 940 x 1285)."""


def uv_source(device: torch.device | str, requested: str = "auto",
              pixels: int | None = None) -> Literal["raster", "raycast", "torch"]:
    """The resolved uv source for a model on ``device`` (``UV_SOURCES``; ValueError naming the choices).
    ``pixels``: an image's size where its uvs are made in the rendering process (None in the data workers); on
    CUDA, ``auto`` takes the torch rasteriser above ``RASTER_MAX_PIXELS_ON_GPU``."""
    check_uv_source(requested)
    if requested == "auto":
        cuda = torch.device(device).type == "cuda"
        if raster_kernel_available() and not (cuda and pixels is not None and pixels > RASTER_MAX_PIXELS_ON_GPU):
            return "raster"
        return "torch" if cuda else "raycast"
    return requested  # type: ignore[return-value]


# one torch rasteriser per frame geometry (its ray caster) and device, alive as long as the ray caster
_TORCH_RASTERIZERS: "weakref.WeakKeyDictionary[UVRaycaster, dict[torch.device, TorchUVRasterizer]]" = \
    weakref.WeakKeyDictionary()


def device_camera_rays(raycaster: UVRaycaster, camera: Camera, device: torch.device | str, uv: str = "auto",
                       viewdir: bool = True) -> CameraRays:
    """The shaded rays of ``camera`` from ``uv_source(device, uv)``: the ray caster's or the C rasteriser's of
    the same frame (numpy), or the torch rasteriser's on ``device`` (tensors; built once per ray caster and
    device). ``viewdir=False``: the rasterisers leave the view directions out."""
    device = torch.device(device)
    source = uv_source(device, uv, camera.width * camera.height)
    if source == "raycast":
        return camera_rays(raycaster, camera)
    if source == "raster":
        return rasterized_camera_rays(raycaster, camera, viewdir=viewdir)
    per_device = _TORCH_RASTERIZERS.setdefault(raycaster, {})
    if device not in per_device:
        per_device[device] = TorchUVRasterizer(raycaster.inner_verts, raycaster.faces, raycaster.outer_verts,
                                               raycaster.atlas, device)
    return torch_camera_rays(per_device[device], camera, viewdir, fallback=raycaster)


def raster_frame_rays(inner_verts: np.ndarray, outer_verts: np.ndarray, faces: np.ndarray, atlas: UVAtlas,
                      cameras: Sequence[Camera]) -> list[CameraRays]:
    """``frame_rays`` by the C rasteriser (:func:`~deliffas.fast.rasterize.rasterized_camera_rays`, the surfaces as
    ``frame_rays`` casts them: float32); the ray caster's scenes are built only for a camera with a vertex behind
    it (needs open3d)."""
    raycaster = UVRaycaster(np.asarray(inner_verts, np.float32), faces, np.asarray(outer_verts, np.float32), atlas)
    return [rasterized_camera_rays(raycaster, cam) for cam in cameras]


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
    return CameraRays.from_shaded(got, camera)


def torch_frame_rays(inner_verts: np.ndarray, outer_verts: np.ndarray, faces: np.ndarray, atlas: UVAtlas,
                     cameras: Sequence[Camera], device: torch.device | str) -> list[CameraRays]:
    """``frame_rays`` by the torch rasteriser on ``device`` (the surfaces as ``frame_rays`` casts them: float32)."""
    rasterizer = TorchUVRasterizer(np.asarray(inner_verts, np.float32), faces, np.asarray(outer_verts, np.float32),
                                   atlas, device)
    return [torch_camera_rays(rasterizer, cam) for cam in cameras]
