"""Data pipeline: conversion frames/s, loader samples/s (0 and 2 workers) against the PNG folder, bytes on disk."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._capture import bench_capture, capture_size
from benchmarks.common import Result, sized

K = 4


def _png_item(root: Path, frame: int, cams: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The same sample read from the DELIFFAS per-frame PNG layout: K RGBA PNGs -> float images, masks."""
    import cv2

    imgs, masks = [], []
    for c in cams:
        bgra = cv2.imread(str(root / f"{frame:06d}" / f"image_alp_c_{c:03d}_f_{frame:06d}.png"), cv2.IMREAD_UNCHANGED)
        imgs.append(bgra[..., 2::-1])
        masks.append(bgra[..., 3])
    return (torch.from_numpy(np.stack(imgs)).float().div_(255.0), torch.from_numpy(np.stack(masks)).float().div_(255.0))


def _loader_rate(ds, indices, workers: int) -> float:
    from torch.utils.data import DataLoader

    loader = DataLoader(ds, batch_size=None, sampler=indices, num_workers=workers,
                        persistent_workers=False, prefetch_factor=4 if workers else None)
    it = iter(loader)
    next(it)  # worker start-up is not throughput
    t0 = time.perf_counter()
    n = sum(1 for _ in it)
    return n / (time.perf_counter() - t0)


def run() -> list[Result]:
    from deliffas.data.dataset import ShardDataset

    subject, shards, convert_s = bench_capture()
    dims = capture_size()
    n_frames = dims.frames + dims.test_frames
    tries = sized(2, 1)
    png_root = next((subject / "training").glob("rgb_*"))
    png_bytes = sum(p.stat().st_size for p in png_root.rglob("*.png"))
    ds = ShardDataset(shards, split="train", cameras_per_item=K, protocol="all")
    shard_image_bytes = 0
    import h5py

    for p in (shards / "shards").glob("*.h5"):
        with h5py.File(p, "r") as f:
            if "rgba" in f:
                shard_image_bytes += f["rgba"].id.get_storage_size()
    rows = [Result("data", f"convert {n_frames} frames x {dims.cameras} cams {dims.size}^2 (jobs 1, incl. setup)",
                   n_frames / convert_s, "frames/s"),
            Result("data", "image bytes in shards / PNG folder bytes", shard_image_bytes / png_bytes, "ratio",
                   note=f"{shard_image_bytes / 1e6:.2f} MB vs {png_bytes / 1e6:.2f} MB")]
    # random frames and cameras, as RandomCameraSampler draws them: a sequential sweep would let
    # the h5py chunk cache serve the overlapping temporal windows of consecutive frames
    rng = np.random.default_rng(0)
    indices = [(int(rng.integers(len(ds.frames))), tuple(int(c) for c in rng.choice(ds.cameras, K, replace=False)))
               for _ in range(3 * len(ds.frames))]

    def png_rate() -> float:
        t = time.perf_counter()
        for pos, c in indices:
            _png_item(png_root, ds.frames[pos], list(c))
        return len(indices) / (time.perf_counter() - t)

    png_only = max(png_rate() for _ in range(tries))
    rows.append(Result("data", f"PNG folder: K={K} images+masks only (no geometry)", png_only, "samples/s"))
    geometry = _geometry_from_motion(subject, ds)

    def png_sample_rate() -> float:
        t = time.perf_counter()
        for pos, c in indices:
            _png_item(png_root, ds.frames[pos], list(c))
            geometry(ds.frames[pos])
        return len(indices) / (time.perf_counter() - t)

    png = max(png_sample_rate() for _ in range(tries))
    rows.append(Result("data", f"PNG folder + pose/normal maps from the motion (same sample)", png, "samples/s"))
    for workers in (0, 2):
        rate = max(_loader_rate(ds, indices, workers) for _ in range(tries))
        rows.append(Result("data", f"ShardDataset, {workers} workers (images, masks, normal maps, verts)", rate,
                           "samples/s", baseline="PNG + geometry", ratio=rate / png,
                           target=">= 5" if workers == 0 else "", passed=(rate / png >= 5) if workers == 0 else None,
                           note=f"{rate / png_only:.2f}x the images-only PNG read"))
    return rows


def _geometry_from_motion(subject: Path, ds):
    """What a sample needs besides the images when there are no shards: pose the window, build normal maps."""
    from deliffas.io.formats.dynacap.character import read_character, read_motion
    from deliffas.geometry.atlas import UVAtlas, uv_texel_table
    from deliffas.geometry.frame_geometry import FrameGeometryBuilder
    from deliffas.geometry.templates import DDCTemplate

    meta = ds.shards.meta
    character = read_character(meta.attrs["character_path"])
    motion = read_motion(next((subject / "training").glob("*.motion")), character.skeleton.num_dofs)
    template = DDCTemplate(character, dtype=torch.float32)
    table = uv_texel_table(UVAtlas(character.mesh.uvs, character.mesh.face_uvs), meta.atlas_res)
    builder = FrameGeometryBuilder(character.mesh.faces, meta.outer_offsets, table, dtype=torch.float16)
    T = ds.temporal_window

    def geometry(frame: int):
        rows = [motion.row_of(max(frame - t, int(motion.frames[0]))) for t in range(T + 1)]
        with torch.no_grad():
            inner = template.pose(torch.as_tensor(motion.dofs[rows], dtype=torch.float32)).numpy()
        return builder.build(inner)

    return geometry
