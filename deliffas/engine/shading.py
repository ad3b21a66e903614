"""Shading cameras with a trained model: a frame's cameras, or one camera, timed per stage (cnn, uv, sample, mlp)."""

from __future__ import annotations

import torch

from deliffas.engine.rays import device_camera_rays, paint_images, ray_query, stack_rays
from deliffas.engine.samples import FrameSample
from deliffas.engine.timing import StageTimer
from deliffas.fast.config import RenderPathConfig
from deliffas.fast.frame import fast_render_camera, path_for_device
from deliffas.io.cameras import Camera
from deliffas.models.deliffas import DeliffasModel, FrameFeatures

__all__ = ["PLAIN", "render_frame", "render_camera"]

PLAIN = RenderPathConfig(path="plain")
"""The reference path (``model.shade`` in chunks), the uvs by ``auto``: the default of the functions below."""


@torch.no_grad()
def render_frame(model: DeliffasModel, sample: FrameSample, raycaster, device: torch.device,
                 timer: StageTimer, chunk_size: int = 262144, render_path: RenderPathConfig = PLAIN) -> torch.Tensor:
    """Render every camera of ``sample`` with per-stage timing; (K, H, W, 3) on black.

    ``sample.rays`` is ignored: the rays are cast here so the ``uv`` stage is timed.
    """
    with timer.stage("cnn"):
        features = model.encode(*sample.normal_maps(device))
    return torch.stack([render_camera(model, features, raycaster, cam, device, timer, chunk_size, render_path)
                        for cam in sample.cameras])


@torch.no_grad()
def render_camera(model: DeliffasModel, features: FrameFeatures, raycaster, camera: Camera, device: torch.device,
                  timer: StageTimer, chunk_size: int = 262144, render_path: RenderPathConfig = PLAIN) -> torch.Tensor:
    """One camera's (H, W, 3) image on black from the frame's encoded ``features`` (stages uv, sample, mlp), by
    ``render_path``: the fast path (``fast.frame``) on a CPU device, else the plain one; the uvs from its ``uv``
    (``deliffas.fast.uv_sources``)."""
    render_path = path_for_device(render_path, device)
    if render_path.fast:
        return fast_render_camera(model, features, raycaster, camera, timer, render_path)
    with timer.stage("uv"):
        batch = stack_rays([device_camera_rays(raycaster, camera, device, render_path.uv)], [0]).to(device)
        query = ray_query(batch, model.spec)
    pred_parts = []
    for part in query.chunks(chunk_size):
        with timer.stage("sample"):
            encoded, feats = model.gather_inputs(features, part)
        with timer.stage("mlp"):
            pred_parts.append(model.mlp(encoded, feats))
    return paint_images(torch.cat(pred_parts), batch, 1, camera.height, camera.width)[0]
