"""What the viewer looks at: the trained runs, the capture's cameras and the timeline's frame geometry.

A timeline position is either a captured frame (geometry and temporal normal maps read from the
shards, ground truth available for every converted camera) or a frame of a driving motion (posed
with the capture's template and built exactly as conversion builds it). Recent frames are cached.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from deliffas.data.dataset import ShardDataset
from deliffas.data.pose_motions import read_pose_motion
from deliffas.data.shards import ShardSet
from deliffas.engine.avatar import load_avatar
from deliffas.engine.devices import resolve_device
from deliffas.engine.identity import check_identity, check_run_shards, recorded_shards
from deliffas.engine.render import motion_geometry_builder
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import UVRaycaster
from deliffas.io.cameras import Camera
from deliffas.models.deliffas import DeliffasModel

__all__ = ["FrameData", "ViewRun", "ViewScene"]

logger = logging.getLogger(__name__)

_CACHED_FRAMES = 4


@dataclass(frozen=True)
class FrameData:
    """The geometry of one timeline position.

    Attributes:
        index: position on the timeline.
        capture_frame: the capture's frame number when this is a captured frame, else None.
        inner_verts: (V, 3) float32 mm, posed inner surface.
        outer_verts: (V, 3) float32 mm, outer surface.
        normal_inner: (3 (T + 1), S, S) float32 temporal normal maps (T = the scene's largest window).
        normal_outer: (3 (T + 1), S, S) float32.
        raycaster: the frame's ray-casting scenes.
    """

    index: int
    capture_frame: int | None
    inner_verts: np.ndarray
    outer_verts: np.ndarray
    normal_inner: torch.Tensor
    normal_outer: torch.Tensor
    raycaster: UVRaycaster

    def normal_maps(self, temporal_window: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """(1, 3 (T + 1), S, S) inner and outer maps for a model of window T (frames f ... f - T)."""
        c = 3 * (temporal_window + 1)
        return self.normal_inner[None, :c].to(device), self.normal_outer[None, :c].to(device)


@dataclass(frozen=True)
class ViewRun:
    """A trained run shown by the viewer."""

    name: str
    model: DeliffasModel
    record: dict


class ViewScene:
    """The runs, cameras and timeline of a viewer session (thread-safe frame cache).

    Args:
        runs: run directories (one, or two to compare); they must share the shards.
        shards: shard directory (default: the first run's).
        motion: driving motion file, or None for the capture's own (training) frames.
        device: where the models run.
        max_frames: at most this many motion frames on the timeline.
    """

    def __init__(self, runs: list[str], shards: str | None = None, motion: str | None = None,
                 device: str = "cpu", max_frames: int = 300):
        self.device = resolve_device(device)
        self.runs = []
        captures = []
        for r in runs:  # a run folder or an .avatar file: each carries its capture (no shards needed with a motion)
            model, record, capture = load_avatar(r, self.device)
            self.runs.append(ViewRun(Path(r).name, model, record))
            captures.append(capture)
        for r, run in zip(runs[1:], self.runs[1:]):
            check_identity(self.runs[0].record.get("identity"), str(runs[0]), run.record.get("identity") or {}, str(r))
        recorded = recorded_shards(runs[0], self.runs[0].record)
        shard_set: ShardSet | None = None
        if motion is not None and shards is None and recorded is None:
            meta = captures[0]  # the shards moved: a motion needs only the run's capture record
        else:
            shard_set = check_run_shards(runs[0], self.runs[0].record, shards)  # opened once, passed on
            for r, run in zip(runs[1:], self.runs[1:]):
                check_run_shards(r, run.record, shard_set)
            meta = shard_set.meta
        self.shards = str(shard_set.out_dir) if shard_set else None
        self.meta = meta
        self.cameras: list[Camera] = meta.cameras()
        self.converted_cameras = [int(c) for c in meta.converted_cameras]
        self.test_cameras = [int(c) for c in meta.test_cameras]
        self.faces = np.asarray(meta.faces, np.int64)
        self.atlas = UVAtlas(np.asarray(meta.uvs), np.asarray(meta.face_uvs))
        stored = int(meta.attrs.get("window", 0))
        self.temporal_window = max(run.model.config.temporal_window for run in self.runs)
        if self.temporal_window > stored and motion is None:
            raise ValueError(f"the runs need a temporal window of {self.temporal_window}, the shards store {stored}")
        for run in self.runs:
            if run.model.config.atlas_res != meta.atlas_res:
                raise ValueError(f"run {run.name}: atlas {run.model.config.atlas_res}, shards {meta.atlas_res}")
        self._lock = threading.Lock()
        self._cache: OrderedDict[int, FrameData] = OrderedDict()
        self._motion = None
        if motion is None:
            self._dataset = ShardDataset(shard_set, split="all", cameras_per_item=1,
                                         temporal_window=self.temporal_window, protocol="all")
            self.frame_labels = [int(f) for f in self._dataset.frames]
            self.source = "capture (training frames)"
        else:
            self._dataset = None
            self._template, self._builder = motion_geometry_builder(meta)
            self._motion = read_pose_motion(motion, self.meta.template_spec(), self._template.num_dofs).dofs[:max_frames]
            self.frame_labels = list(range(len(self._motion)))
            self.source = f"motion {Path(motion).name}"
        if not self.frame_labels:
            raise ValueError(f"{self.source}: no frames to show")

    @property
    def num_frames(self) -> int:
        return len(self.frame_labels)

    def frame(self, index: int) -> FrameData:
        """The geometry of timeline position ``index`` (cached)."""
        index = int(np.clip(index, 0, self.num_frames - 1))
        with self._lock:
            if index in self._cache:
                self._cache.move_to_end(index)
                return self._cache[index]
        data = self._load(index)
        with self._lock:
            self._cache[index] = data
            while len(self._cache) > _CACHED_FRAMES:
                self._cache.popitem(last=False)
        return data

    def _load(self, index: int) -> FrameData:
        if self._dataset is not None:
            item = self._dataset[(index, [self.converted_cameras[0]])]
            inner, outer = item.inner_verts.numpy(), item.outer_verts.numpy()
            nm_in, nm_out = item.normal_maps_inner.float(), item.normal_maps_outer.float()
            capture_frame = int(item.frame)
        else:
            T = self.temporal_window
            lo = max(0, index - T)
            posed = self._template.pose(torch.as_tensor(self._motion[lo:index + 1], dtype=torch.float64)).numpy()
            geometry = self._builder.build(posed)
            nm_in, nm_out = geometry.window(index - lo, T)
            inner, outer = geometry.inner[-1], geometry.outer[-1]
            capture_frame = None
        raycaster = UVRaycaster(inner, self.faces, outer, self.atlas)
        return FrameData(index, capture_frame, inner, outer, nm_in, nm_out, raycaster)

    def ground_truth(self, index: int, camera_id: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The captured (H, W, 3) float32 image on black and its (H, W) mask, or None off the capture."""
        if self._dataset is None or camera_id not in self.converted_cameras:
            return None
        item = self._dataset[(int(index), [int(camera_id)])]
        mask = item.masks[0].numpy().astype(np.float32) / 255
        return item.images[0].numpy().astype(np.float32) / 255 * mask[..., None], mask
