"""The per-frame record the engine trains and evaluates on, and its training target.

A ``FrameSample`` is one frame with K cameras: the images and masks, the frame's temporal normal
maps (camera-independent, so the U-Nets run once per frame), the posed surfaces and, per camera,
the shaded rays (``CameraRays``). ``deliffas.engine.data_bridge`` makes them from shards, ray
casting in the DataLoader workers.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from deliffas.io.cameras import Camera
from deliffas.engine.rays import CameraRays

__all__ = ["FrameSample", "composite_target", "subsample_rays"]


@dataclass(frozen=True)
class FrameSample:
    """One frame seen by K cameras.

    Attributes:
        frame: frame index.
        images: (K, H, W, 3) float32 RGB in [0, 1].
        masks: (K, H, W) float32 foreground coverage in [0, 1].
        cameras: K cameras.
        camera_ids: (K,) indices of the cameras in the capture's camera table.
        normal_inner: (3 (T + 1), S, S) float32 temporal normal maps of the inner surface.
        normal_outer: (3 (T + 1), S, S) float32 of the outer surface.
        inner_verts: (V, 3) float32 posed inner surface, mm.
        outer_verts: (V, 3) float32 posed outer surface (offset shell), mm.
        rays: K ray sets (empty when the consumer casts its own, e.g. timed evaluation).
    """

    frame: int
    images: np.ndarray
    masks: np.ndarray
    cameras: list[Camera]
    camera_ids: np.ndarray
    normal_inner: np.ndarray
    normal_outer: np.ndarray
    inner_verts: np.ndarray
    outer_verts: np.ndarray
    rays: list[CameraRays]

    @property
    def num_cameras(self) -> int:
        return len(self.cameras)

    def normal_maps(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """The U-Nets' inputs: inner and outer temporal normal maps, each (1, 3 (T + 1), S, S) on
        ``device`` (``DeliffasModel.encode`` ignores the outer one when the variant has no outer U-Net)."""
        return (torch.from_numpy(self.normal_inner)[None].to(device),
                torch.from_numpy(self.normal_outer)[None].to(device))


def composite_target(images: np.ndarray | torch.Tensor, masks: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Training target: (K, H, W, 3) images in [0, 1] over a black background by the (K, H, W) masks.

    ``images`` hold straight colour (not premultiplied by the mask), as a photograph and its
    foreground coverage, and as ``synth`` writes them: a fractional mask (a supersampled edge) blends
    the colour with the background.

    The model paints every ray that meets the outer shell; pixels of the shell that are not the
    person must come out as the background, so the target is defined everywhere.
    """
    return torch.as_tensor(images).float() * torch.as_tensor(masks).float()[..., None]


def subsample_rays(sample: FrameSample, count: int, rng: np.random.Generator) -> FrameSample:
    """``sample`` with at most ``count`` of its shaded rays: a uniform random subset of the K cameras' rays
    together (without replacement, each camera's in pixel order). Unchanged when it has ``count`` or fewer."""
    sizes = [r.num_rays for r in sample.rays]
    total = sum(sizes)
    if total <= count:
        return sample
    keep = np.zeros(total, bool)
    keep[rng.choice(total, size=count, replace=False)] = True
    rays, start = [], 0
    for r, n in zip(sample.rays, sizes):
        sel = keep[start:start + n]
        start += n
        if isinstance(r.pixels, torch.Tensor):
            sel = torch.from_numpy(sel).to(r.pixels.device)
        rays.append(CameraRays(r.pixels[sel], r.uv_inner[sel], r.inner_from_outer[sel], r.uv_outer[sel],
                               None if r.viewdir is None else r.viewdir[sel], r.height, r.width))
    return dataclasses.replace(sample, rays=rays)
