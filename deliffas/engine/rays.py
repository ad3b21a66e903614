"""Per-camera ray sets of one frame, from the uv source a device asks for.

The uv sources (the C rasteriser, the open3d ray caster, the torch rasteriser) and the resolution of ``auto``
sit side by side in :mod:`deliffas.fast.uv_sources`; the rays themselves and the way to the model are lower down.
All are re-exported here for the engine: the ray caster's :class:`~deliffas.geometry.camera_rays.CameraRays`
(:func:`camera_rays`, :func:`frame_rays`) and the model's side (:func:`~deliffas.models.ray_query.stack_rays`,
:func:`ray_query`, :func:`paint_images`, :class:`RayBatch`).
"""

from __future__ import annotations

from deliffas.fast.config import UV_SOURCES, UVSource
from deliffas.fast.uv_sources import (RASTER_MAX_PIXELS_ON_GPU, device_camera_rays, raster_frame_rays,
                                      torch_camera_rays, torch_frame_rays, uv_source)
from deliffas.geometry.camera_rays import CameraRays, camera_rays, frame_rays
from deliffas.models.ray_query import RayBatch, paint_images, ray_query, stack_rays

__all__ = ["CameraRays", "camera_rays", "frame_rays", "RayBatch", "stack_rays", "ray_query", "paint_images",
           "UVSource", "UV_SOURCES", "RASTER_MAX_PIXELS_ON_GPU", "uv_source", "torch_camera_rays", "torch_frame_rays",
           "raster_frame_rays", "device_camera_rays"]
