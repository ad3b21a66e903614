"""ShardDataset: item shapes, DataLoader workers, protocol splits, the random camera sampler."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import DataLoader

from deliffas.data.dataset import FrameItem, RandomCameraSampler, ShardDataset, protocol_frames
from deliffas.io.formats.dynacap.frames import ImageFolderSource
from deliffas.data.shards import read_manifest, write_manifest


def test_item_shapes_and_values(subject, converted):
    ds = ShardDataset(converted, "train", cameras_per_item=2, temporal_window=2, protocol="all")
    assert ds.cameras == [0, 1, 3] and ds.frames == [0, 1, 2] and len(ds) == 3 * 2  # groups [0, 1], [3]
    item = ds[2]  # frame 1, cameras 0 and 1
    assert isinstance(item, FrameItem)
    V = ds.shards.meta.rest_verts.shape[0]
    D = ds.shards.locate("training", 0)[0].h5["geometry/dofs"].shape[1]
    shapes = {k: tuple(v.shape) for k, v in item._asdict().items()}
    assert shapes == {"images": (2, 64, 64, 3), "masks": (2, 64, 64), "intrinsics": (2, 3, 3),
                      "world_to_cam": (2, 4, 4), "camera_ids": (2,), "inner_verts": (V, 3), "outer_verts": (V, 3),
                      "normal_maps_inner": (9, 32, 32), "normal_maps_outer": (9, 32, 32), "dofs": (D,), "frame": ()}
    assert item.images.dtype == torch.uint8 and item.masks.dtype == torch.uint8
    assert item.normal_maps_inner.dtype == torch.float16
    assert int(item.frame) == 1 and item.camera_ids.tolist() == [0, 1]
    ref_rgb, ref_mask = ImageFolderSource(subject / "training").read(1, 1)
    assert torch.equal(item.images[1], torch.from_numpy(ref_rgb))
    assert torch.equal(item.masks[1], torch.from_numpy(ref_mask))
    # temporal window: channels 3:6 are frame 0, 6:9 clamp to frame 0 as well
    first = ds[0]
    assert torch.equal(item.normal_maps_inner[3:6], first.normal_maps_inner[0:3])
    assert torch.equal(item.normal_maps_inner[6:9], first.normal_maps_inner[0:3])
    assert not torch.equal(item.normal_maps_inner[0:3], item.normal_maps_inner[3:6])
    assert ds[5].camera_ids.tolist() == [3]  # last, shorter group of frame 2
    with pytest.raises(ValueError, match="--window 3"):
        ShardDataset(converted, temporal_window=3)


def test_paper_protocol_splits(converted):
    assert protocol_frames(range(100, 131), 100, "paper") == [100, 110, 120, 130]
    assert protocol_frames([3, 13, 14, 23], 3, "paper") == [3, 13, 23]
    train = ShardDataset(converted, "train")
    view = ShardDataset(converted, "novel_view")
    pose = ShardDataset(converted, "novel_pose")
    assert train.cameras == [0, 1, 3] and view.cameras == [2] and pose.cameras == [2]
    assert train.frames == [0] and view.frames == [0] and pose.frames == [0] and pose.sequence == "testing"
    assert ShardDataset(converted, "novel_pose", protocol="all").cameras == [0, 1, 2, 3]
    assert ShardDataset(converted, "all", protocol="all").frames == [0, 1, 2]
    assert ShardDataset(converted, "train", frames=[2, 7], cameras=[3]).frames == [2]
    with pytest.raises(ValueError, match="not converted"):
        ShardDataset(converted, "train", cameras=[9])


def test_dataloader_with_workers_and_sampler(converted):
    ds = ShardDataset(converted, "train", cameras_per_item=2, protocol="all")
    sampler = RandomCameraSampler(ds, generator=torch.Generator().manual_seed(0))
    draws = list(sampler)
    assert sorted(p for p, _ in draws) == [0, 1, 2]
    assert all(len(c) == 2 and len(set(c)) == 2 and set(c) <= {0, 1, 3} for _, c in draws)
    assert draws == list(RandomCameraSampler(ds, generator=torch.Generator().manual_seed(0)))
    ds[0]  # open handles in the parent first: workers must not reuse them
    sampler.generator.manual_seed(0)
    loader = DataLoader(ds, sampler=sampler, batch_size=3, num_workers=2)
    batches = list(loader)
    assert len(batches) == 1
    b = batches[0]
    assert b.images.shape == (3, 2, 64, 64, 3) and b.normal_maps_outer.shape == (3, 9, 32, 32)
    for k, (pos, cams) in enumerate(RandomCameraSampler(ds, generator=torch.Generator().manual_seed(0))):
        ref = ds[(pos, cams)]
        assert torch.equal(b.images[k], ref.images) and b.camera_ids[k].tolist() == list(cams)


def test_refresh_sees_new_shards(converted_copy):
    full = read_manifest(converted_copy)
    partial = dict(full, shards=full["shards"][:1], complete=False)
    write_manifest(converted_copy, partial)
    ds = ShardDataset(converted_copy, "train", protocol="all")
    assert ds.frames == [0, 1]
    write_manifest(converted_copy, full)
    ds.refresh()
    assert ds.frames == [0, 1, 2]
