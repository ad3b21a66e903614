"""torch Dataset over converted shards: one frame with K cameras per item, plus a random-camera sampler.

Splits (dynacap-formats.md 3.9): ``train`` = training sequence x training cameras; ``novel_view`` =
training sequence x held-out cameras; ``novel_pose`` = testing sequence x held-out cameras (protocol
``paper``) or x every converted camera (protocol ``all``); ``all`` = training sequence x every converted
camera. Protocol ``paper`` keeps every 10th frame counted from the sequence's first frame (DELIFFAS
trains and tests on ``range(start, end, 10)``), ``all`` keeps every converted frame.

Items are ``FrameItem`` named tuples (``default_collate`` stacks them). h5py handles are opened lazily
in the process that reads (each DataLoader worker opens its own; nothing is shared across fork).
"""

from __future__ import annotations

import math
import os
from typing import Literal, NamedTuple, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler
from jaxtyping import Float, Integer, UInt8
from torch import Tensor

from deliffas.data.shards import ShardReadError, ShardSet, open_shard_set

__all__ = ["ShardDataset", "FrameItem", "RandomCameraSampler", "protocol_frames", "PAPER_FRAME_STEP", "SPLITS"]

PAPER_FRAME_STEP = 10
"""DELIFFAS uses every 10th frame for training and for testing."""
SPLITS = ("train", "novel_view", "novel_pose", "all")
Split = Literal["train", "novel_view", "novel_pose", "all"]
Protocol = Literal["paper", "all"]


class FrameItem(NamedTuple):
    """One frame seen by K cameras (leading batch dimension B after collation).

    Attributes:
        images: (K, H, W, 3) uint8 RGB (as stored; divide by 255 where the model runs, e.g. on the GPU).
        masks: (K, H, W) uint8 foreground coverage (255 = covered).
        intrinsics: (K, 3, 3) float32, pixels, for the stored image size (pixel-corner convention).
        world_to_cam: (K, 4, 4) float32, world mm -> camera mm.
        camera_ids: (K,) int64 calibration indices.
        inner_verts: (V, 3) float32 mm, world frame, posed inner surface of the frame.
        outer_verts: (V, 3) float32 mm, world frame, outer surface (offset shell).
        normal_maps_inner: (3 (T + 1), S, S) float16 as stored, unit world-space normals in [-1, 1]
            (0 off the atlas), frames f, f-1, ..., f-T (clamped at the sequence's first frame).
        normal_maps_outer: (3 (T + 1), S, S) float16, the same for the outer surface.
        dofs: (D,) float32 pose parameters of the frame (the template's units).
        frame: () int64 capture frame number (not a row).
    """

    images: UInt8[Tensor, "K H W 3"]
    masks: UInt8[Tensor, "K H W"]
    intrinsics: Float[Tensor, "K 3 3"]
    world_to_cam: Float[Tensor, "K 4 4"]
    camera_ids: Integer[Tensor, "K"]
    inner_verts: Float[Tensor, "V 3"]
    outer_verts: Float[Tensor, "V 3"]
    normal_maps_inner: Float[Tensor, "C S S"]
    normal_maps_outer: Float[Tensor, "C S S"]
    dofs: Float[Tensor, "D"]
    frame: Integer[Tensor, ""]


def protocol_frames(frames: Sequence[int], first_frame: int, protocol: Protocol) -> list[int]:
    """The frames a protocol keeps: ``paper`` = (f - first_frame) % 10 == 0, ``all`` = every frame."""
    if protocol == "all":
        return sorted(int(f) for f in frames)
    if protocol == "paper":
        return sorted(int(f) for f in frames if (int(f) - first_frame) % PAPER_FRAME_STEP == 0)
    raise ValueError(f"protocol must be 'paper' or 'all', got {protocol!r}")


class ShardDataset(Dataset):
    """Frames x camera groups of one split of a converted capture.

    Args:
        shards_dir: output folder of ``deliffas convert`` (complete shards listed by its manifest), or its
            ``ShardSet`` already opened by the command.
        split: ``train``, ``novel_view``, ``novel_pose`` or ``all`` (module docstring).
        cameras: calibration indices overriding the split's cameras.
        frames: capture frames overriding the protocol's frames (intersected with converted frames).
        cameras_per_item: K; an integer index enumerates (frame, consecutive group of K cameras), the
            last group of a frame may be shorter; None = every camera of the split in one item.
        temporal_window: T <= the stored window.
        protocol: ``paper`` (every 10th frame, held-out cameras for novel poses) or ``all``.

    Indexing: ``dataset[i]`` with an int, or ``dataset[(frame_pos, camera_ids)]`` as yielded by
    ``RandomCameraSampler``.
    """

    def __init__(self, shards_dir: ShardSet | str | os.PathLike, split: Split = "train",
                 cameras: Sequence[int] | None = None, frames: Sequence[int] | None = None,
                 cameras_per_item: int | None = 1, temporal_window: int = 2, protocol: Protocol = "paper"):
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if protocol not in ("paper", "all"):
            raise ValueError(f"protocol must be 'paper' or 'all', got {protocol!r}")
        self.shards = open_shard_set(shards_dir)
        meta = self.shards.meta
        stored = int(meta.attrs.get("window", 0))
        if not 0 <= temporal_window <= stored:
            raise ValueError(f"temporal_window {temporal_window}: the shards store T <= {stored} "
                             f"(convert with --window {temporal_window})")
        self.split, self.protocol, self.temporal_window = split, protocol, int(temporal_window)
        self.sequence = "testing" if split == "novel_pose" else "training"
        converted = [int(c) for c in meta.converted_cameras]
        if cameras is not None:
            cams = [int(c) for c in cameras]
            bad = [c for c in cams if c not in converted]
            if bad:
                raise ValueError(f"cameras {bad} were not converted (converted: {converted})")
        elif split == "train":
            cams = [int(c) for c in meta.train_cameras]
        elif split == "all" or (split == "novel_pose" and protocol == "all"):
            cams = converted
        else:
            cams = [int(c) for c in meta.test_cameras]
        if not cams:
            raise ValueError(f"split {split!r}: no cameras (the capture has no held-out test cameras?)")
        self.cameras = cams
        self.cameras_per_item = len(cams) if cameras_per_item is None else int(cameras_per_item)
        if self.cameras_per_item < 1:
            raise ValueError(f"cameras_per_item must be >= 1, got {cameras_per_item}")
        self._frames_arg = None if frames is None else [int(f) for f in frames]
        self._select_frames()
        self._K = torch.as_tensor(meta.K, dtype=torch.float32)
        self._E = torch.as_tensor(meta.world_to_cam, dtype=torch.float32)

    def _select_frames(self) -> None:
        meta = self.shards.meta
        if self.sequence not in meta.sequence_frames:
            raise ValueError(f"split {self.split!r} needs the {self.sequence} sequence, which was not converted")
        available = self.shards.frames(self.sequence)
        if self._frames_arg is not None:
            keep = set(available)
            self.frames = [f for f in self._frames_arg if f in keep]
        else:
            self.frames = protocol_frames(available, meta.first_frames[self.sequence], self.protocol)
        self.groups = math.ceil(len(self.cameras) / self.cameras_per_item)

    def refresh(self) -> None:
        """Re-read the manifest: frames of shards finished since construction become items."""
        self.shards.refresh()
        self._select_frames()

    def __len__(self) -> int:
        return len(self.frames) * self.groups

    def _resolve(self, index) -> tuple[int, list[int]]:
        if isinstance(index, (tuple, list)) and len(index) == 2:
            pos, cams = index
            return int(pos), [int(c) for c in (cams.tolist() if isinstance(cams, torch.Tensor) else cams)]
        i = int(index)
        if not 0 <= i < len(self):
            raise IndexError(f"index {i} outside [0, {len(self)})")
        pos, g = divmod(i, self.groups)
        k = self.cameras_per_item
        return pos, self.cameras[g * k:(g + 1) * k]

    def __getitem__(self, index) -> FrameItem:
        pos, cams = self._resolve(index)
        frame = self.frames[pos]
        shard, row = self.shards.locate(self.sequence, frame)
        try:
            return self._read(shard, row, frame, cams)
        except (OSError, KeyError, ValueError, IndexError, TypeError) as err:  # h5py's errors on damaged files
            raise ShardReadError(f"{shard.path}: cannot read frame {frame} ({type(err).__name__}: "
                                 f"{str(err)[:160]}); run `deliffas verify {self.shards.out_dir}`") from err

    def _read(self, shard, row: int, frame: int, cams: list[int]) -> FrameItem:
        col_of = {int(c): j for j, c in enumerate(shard.camera_ids)}
        rgba = torch.from_numpy(shard.rgba_many(row, [col_of[c] for c in cams]))  # (K, H, W, 4) uint8
        T = self.temporal_window
        wrows = shard.dataset("window_rows")[row][: T + 1]
        nm_in = shard.geometry("normal_maps_inner", wrows)  # (T+1, 3, S, S)
        nm_out = shard.geometry("normal_maps_outer", wrows)
        S = nm_in.shape[-1]
        r0 = int(wrows[0])
        cam_idx = torch.as_tensor(cams, dtype=torch.long)
        return FrameItem(
            # Stored dtypes: the float conversion belongs where the model runs (4x fewer bytes to move).
            images=rgba[..., :3],
            masks=rgba[..., 3],
            intrinsics=self._K[cam_idx],
            world_to_cam=self._E[cam_idx],
            camera_ids=cam_idx,
            inner_verts=torch.from_numpy(shard.geometry("inner_verts", [r0])[0]),
            outer_verts=torch.from_numpy(shard.geometry("outer_verts", [r0])[0]),
            normal_maps_inner=torch.from_numpy(nm_in.reshape(3 * (T + 1), S, S)),
            normal_maps_outer=torch.from_numpy(nm_out.reshape(3 * (T + 1), S, S)),
            dofs=torch.from_numpy(shard.geometry("dofs", [r0])[0].astype(np.float32)),
            frame=torch.tensor(frame, dtype=torch.long),
        )


class RandomCameraSampler(Sampler):
    """Per epoch every frame once (random order), each with K distinct random cameras of the split.

    Yields ``(frame_pos, camera_ids)`` indices for ``ShardDataset``.

    Args:
        dataset: the dataset.
        cameras_per_item: K (default: the dataset's ``cameras_per_item``), at most the split's cameras.
        generator: torch.Generator for reproducible draws (a fresh unseeded one when None).
    """

    def __init__(self, dataset: ShardDataset, cameras_per_item: int | None = None,
                 generator: torch.Generator | None = None):
        self.dataset = dataset
        self.k = int(cameras_per_item or dataset.cameras_per_item)
        if not 1 <= self.k <= len(dataset.cameras):
            raise ValueError(f"cameras_per_item {self.k}: the split has {len(dataset.cameras)} cameras")
        self.generator = generator

    def __len__(self) -> int:
        return len(self.dataset.frames)

    def __iter__(self):
        g = self.generator
        cams = torch.as_tensor(self.dataset.cameras)
        n = len(self.dataset.frames)
        order = torch.randperm(n, generator=g)
        picks = torch.argsort(torch.rand(n, len(cams), generator=g), dim=1)[:, : self.k]  # (n, K) distinct
        for i in range(n):  # one index per item
            yield int(order[i]), tuple(int(c) for c in cams[picks[i]].sort().values)
