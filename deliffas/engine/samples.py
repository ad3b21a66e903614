"""The per-frame training/evaluation record the engine consumes, and its ray-casting collate.

A ``FrameSample`` is one frame with K cameras: the images and masks, the frame's temporal normal
maps (camera-independent, so the U-Nets run once per frame) and, per camera, the shaded rays
(``CameraRays``) ray-cast from the frame's posed inner and outer surfaces. Ray casting runs in
the DataLoader workers (``RayCastCollate``), overlapping with the model's work.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from deliffas.data.cameras import Camera
from deliffas.engine.rays import CameraRays, frame_rays
from deliffas.geometry.atlas import UVAtlas

__all__ = ["FrameSample", "RayCastCollate", "composite_target"]


@dataclass(frozen=True)
class FrameSample:
    """One frame seen by K cameras.

    Attributes:
        frame: frame index.
        images: (K, H, W, 3) uint8 RGB.
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


def composite_target(images: np.ndarray | torch.Tensor, masks: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Training target: RGB over a black background by the mask, (K, H, W, 3) float in [0, 1].

    The model paints every ray that meets the outer shell; pixels of the shell that are not the
    person must come out as the background, so the target is defined everywhere.
    """
    img = torch.as_tensor(images).float() / 255.0
    m = torch.as_tensor(masks).float()[..., None]
    return img * m


class RayCastCollate:
    """DataLoader ``collate_fn`` turning a shard item into a ``FrameSample`` (batch size 1).

    Args:
        faces: (F, 3) template faces.
        atlas: the template's UV atlas (per-corner uvs).
    """

    def __init__(self, faces: np.ndarray, atlas: UVAtlas, with_rays: bool = True):
        self.faces = np.asarray(faces, dtype=np.int64)
        self.atlas = atlas
        self.with_rays = with_rays

    def __call__(self, items: Sequence[dict]) -> FrameSample:
        if len(items) != 1:
            raise ValueError(f"RayCastCollate: one frame per batch (K cameras inside it), got {len(items)}")
        return self.make_sample(items[0])

    def make_sample(self, item: dict) -> FrameSample:
        cameras: list[Camera] = item["cameras"]
        rays = (frame_rays(item["inner_verts"], item["outer_verts"], self.faces, self.atlas, cameras)
                if self.with_rays else [])
        return FrameSample(
            frame=int(item["frame"]),
            images=np.asarray(item["images"]),
            masks=np.asarray(item["masks"], dtype=np.float32),
            cameras=cameras,
            camera_ids=np.asarray(item["camera_ids"]),
            normal_inner=np.asarray(item["normal_inner"], dtype=np.float32),
            normal_outer=np.asarray(item["normal_outer"], dtype=np.float32),
            inner_verts=np.asarray(item["inner_verts"], dtype=np.float32),
            outer_verts=np.asarray(item["outer_verts"], dtype=np.float32),
            rays=rays,
        )
