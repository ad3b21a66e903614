"""``meta.h5``: what every shard of a conversion shares (cameras, split, template, texel table), as a record.

Written once per conversion, atomically and with deterministic bytes (docs/shards.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from jaxtyping import Bool, Float, Integer

from deliffas.io.cameras import Camera
from deliffas.io.infra.files import durable_replace, sha256_file, temp_path
from deliffas.geometry.templates import TemplateSpec, ddc_spec

__all__ = ["ShardMeta", "write_meta", "read_meta", "META_FORMAT", "SCHEMA_VERSION"]

META_FORMAT = "deliffas-meta"
SCHEMA_VERSION = 1
"""Schema version of a shard set: ``meta.h5``, the shards and the manifest."""


@dataclass(frozen=True)
class ShardMeta:
    """Contents of ``meta.h5``.

    Attributes:
        camera_names: calibration names of every calibrated camera (C_all).
        K: (C_all, 3, 3) float64 intrinsics in pixels for the stored image size (pixel corners at
            integers).
        world_to_cam: (C_all, 4, 4) float64, world mm -> camera mm.
        sizes: (C_all, 2) int64 (W, H) of the stored images.
        converted_cameras: (C,) int64 calibration indices whose images the shards hold.
        train_cameras / test_cameras: calibration indices (subsets of ``converted_cameras``).
        sequence_frames: per sequence the selected frames (sorted int64).
        first_frames: per sequence the first frame of its motion (temporal-window clamp).
        faces: (F, 3) int64; uvs (T, 2) float64; face_uvs (F, 3) int64; rest_verts (V, 3) float64.
        outer_offsets: (V,) float32 mm, the per-vertex offset d of the outer surface.
        texel_face: (S, S) int32 face of each texel (-1 off the atlas); texel_bary (S, S, 3) float32;
            texel_valid (S, S) bool.
        attrs: conversion settings and provenance (character path and sha256, codec, window, …).
    """

    camera_names: list[str]
    K: Float[np.ndarray, "Call 3 3"]
    world_to_cam: Float[np.ndarray, "Call 4 4"]
    sizes: Integer[np.ndarray, "Call 2"]
    converted_cameras: Integer[np.ndarray, "C"]
    train_cameras: Integer[np.ndarray, "Ctrain"]
    test_cameras: Integer[np.ndarray, "Ctest"]
    sequence_frames: dict[str, np.ndarray]
    first_frames: dict[str, int]
    faces: Integer[np.ndarray, "F 3"]
    uvs: Float[np.ndarray, "T 2"]
    face_uvs: Integer[np.ndarray, "F 3"]
    rest_verts: Float[np.ndarray, "V 3"]
    outer_offsets: Float[np.ndarray, "V"]
    texel_face: Integer[np.ndarray, "S S"]
    texel_bary: Float[np.ndarray, "S S 3"]
    texel_valid: Bool[np.ndarray, "S S"]
    attrs: dict = field(default_factory=dict)

    def cameras(self) -> list[Camera]:
        """Every calibrated camera, at the stored image size."""
        return [Camera(n, self.K[i].copy(), self.world_to_cam[i].copy(), int(self.sizes[i, 0]), int(self.sizes[i, 1]))
                for i, n in enumerate(self.camera_names)]

    @property
    def atlas_res(self) -> int:
        return int(self.texel_face.shape[0])

    def template_spec(self) -> TemplateSpec:
        """The template the shards were made with (``attrs["template_spec"]``; shard sets written before
        specs were recorded name a DDC ``.character`` and its skinning instead)."""
        if "template_spec" in self.attrs:
            return TemplateSpec.from_json(self.attrs["template_spec"])
        character = self.attrs.get("character_path", "")
        if not character or not Path(character).is_file():
            raise FileNotFoundError(f"{character or '(none recorded)'}: the character the shards were made with is gone")
        return ddc_spec(character, self.attrs.get("skinning", "dqs"), self.attrs.get("outer_obj") or None)


def write_meta(path: str | os.PathLike, meta: ShardMeta) -> tuple[str, int]:
    """Write ``meta.h5`` atomically (deterministic bytes); returns (sha256, bytes)."""
    import h5py

    p = Path(path)
    tmp = temp_path(p)
    with h5py.File(tmp, "w", rdcc_nbytes=0) as f:  # no chunk cache: see ShardWriter
        f.attrs.update({"format": META_FORMAT, "version": SCHEMA_VERSION})
        for k, v in sorted(meta.attrs.items()):
            f.attrs[k] = v
        c = f.create_group("cameras")
        c.create_dataset("names", data=np.array(meta.camera_names, dtype=h5py.string_dtype()))
        c.create_dataset("K", data=np.asarray(meta.K, np.float64))
        c.create_dataset("world_to_cam", data=np.asarray(meta.world_to_cam, np.float64))
        c.create_dataset("sizes", data=np.asarray(meta.sizes, np.int64))
        s = f.create_group("split")
        s.create_dataset("converted_cameras", data=np.asarray(meta.converted_cameras, np.int64))
        s.create_dataset("train_cameras", data=np.asarray(meta.train_cameras, np.int64))
        s.create_dataset("test_cameras", data=np.asarray(meta.test_cameras, np.int64))
        for seq, frames in sorted(meta.sequence_frames.items()):
            d = s.create_dataset(f"frames_{seq}", data=np.asarray(frames, np.int64))
            d.attrs["first_frame"] = int(meta.first_frames[seq])
        ch = f.create_group("character")
        ch.create_dataset("faces", data=np.asarray(meta.faces, np.int64))
        ch.create_dataset("uvs", data=np.asarray(meta.uvs, np.float64))
        ch.create_dataset("face_uvs", data=np.asarray(meta.face_uvs, np.int64))
        ch.create_dataset("rest_verts", data=np.asarray(meta.rest_verts, np.float64))
        ch.create_dataset("outer_offsets", data=np.asarray(meta.outer_offsets, np.float32))
        ch.create_dataset("texel_face", data=np.asarray(meta.texel_face, np.int32), compression="gzip")
        ch.create_dataset("texel_bary", data=np.asarray(meta.texel_bary, np.float32), compression="gzip")
        ch.create_dataset("texel_valid", data=np.asarray(meta.texel_valid, bool), compression="gzip")
    durable_replace(tmp, p)
    return sha256_file(p), p.stat().st_size


def read_meta(path: str | os.PathLike) -> ShardMeta:
    """Read ``meta.h5`` written by ``write_meta``."""
    import h5py

    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != META_FORMAT:
            raise ValueError(f"{path}: not a deliffas meta file")
        s = f["split"]
        seqs = {k[len("frames_"):]: s[k][()] for k in s if k.startswith("frames_")}
        firsts = {k[len("frames_"):]: int(s[k].attrs["first_frame"]) for k in s if k.startswith("frames_")}
        ch = f["character"]
        attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
        return ShardMeta(
            camera_names=[n.decode() if isinstance(n, bytes) else str(n) for n in f["cameras/names"][()]],
            K=f["cameras/K"][()], world_to_cam=f["cameras/world_to_cam"][()], sizes=f["cameras/sizes"][()],
            converted_cameras=s["converted_cameras"][()], train_cameras=s["train_cameras"][()],
            test_cameras=s["test_cameras"][()], sequence_frames=seqs, first_frames=firsts,
            faces=ch["faces"][()], uvs=ch["uvs"][()], face_uvs=ch["face_uvs"][()], rest_verts=ch["rest_verts"][()],
            outer_offsets=ch["outer_offsets"][()], texel_face=ch["texel_face"][()], texel_bary=ch["texel_bary"][()],
            texel_valid=ch["texel_valid"][()], attrs=attrs)
