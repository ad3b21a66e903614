"""Building one shard of a conversion: a frame range's surfaces, normal maps and images into one HDF5 file.

:class:`ShardBuilder` holds what every shard of a conversion shares (the template, outer offsets,
texel table, the sequences' pose parameters and tracked meshes); it is built once per process
(in-process, or once in each worker of the executor: ``ShardBuilder.create`` is the per-worker
setup) and writes shards with :meth:`ShardBuilder.write`. Geometry runs on one torch thread, so shards are byte-identical whatever
``--jobs`` is.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence, no_type_check

import numpy as np
import torch

from deliffas.io.formats.dynacap.character import read_obj
from deliffas.io.formats.dynacap.frames import FrameSource
from deliffas.io.formats.dynacap.meshes import MeshSequence, read_meshes
from deliffas.geometry.atlas import TexelTable, UVAtlas, uv_texel_table
from deliffas.geometry.frame_geometry import FrameGeometryBuilder
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.templates import Template, build_template
from deliffas.data.shards import Codec, ShardGeometry, ShardWriter
from deliffas.data.subjects import Subject

__all__ = ["ShardTask", "ShardSettings", "ShardBuilder", "single_thread_torch"]


@dataclass(frozen=True)
class ShardTask:
    """One shard to write: its file name, sequence, frames and the frames its temporal windows need."""

    name: str
    sequence: str
    frames: tuple[int, ...]
    geometry_frames: tuple[int, ...]


@dataclass(frozen=True)
class ShardSettings:
    """What a conversion's shards share besides the subject (from ``ConvertConfig``)."""

    out_dir: Path
    cameras: tuple[int, ...]
    """Calibration indices converted, in shard column order."""
    atlas_res: int
    gutter: int
    offset_mm: float
    window: int
    codec: str


@contextlib.contextmanager
def single_thread_torch():
    """Geometry runs with one torch thread so results do not depend on --jobs (and workers do not oversubscribe)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _outer_offsets(template: Template, outer_obj: str | None, offset_mm: float) -> np.ndarray:
    """(V,) float32 outer-surface offset per vertex: a variant's ``outer.obj`` along the rest normals, or d."""
    if outer_obj is None:
        return np.full(template.num_verts, offset_mm, np.float32)
    outer = read_obj(outer_obj)
    if outer.num_verts != template.num_verts:
        raise ValueError(f"{outer_obj}: {outer.num_verts} vertices, template has {template.num_verts}")
    rest = template.rest_verts.numpy().astype(np.float64)
    n_rest = vertex_normals(rest, template.faces.numpy())
    return np.einsum("vc,vc->v", outer.verts - rest, n_rest).astype(np.float32)


_OPEN_SOURCES_LOCK = threading.Lock()


@dataclass(frozen=True)
class ShardBuilder:
    """What every shard of one conversion shares (build with :meth:`create`)."""

    subject: Subject
    settings: ShardSettings
    template: Template
    """Built from ``subject.template`` in float64."""
    offsets: np.ndarray
    """(V,) float32 outer offsets, mm."""
    table: TexelTable
    geometry: FrameGeometryBuilder
    meshes: Mapping[str, MeshSequence]
    """Tracked surfaces by sequence (those the subject gives)."""
    open_sources: dict[str, FrameSource] = field(default_factory=dict, compare=False, repr=False)
    """Frame sources kept open across shards, by sequence: those whose spec sets ``keep_open`` (read in any order
    at one cost, slow to open: a DNA-Rendering ``.smc`` is scanned whole at each open). :meth:`close` closes them."""

    # no_type_check: Dask ships this bound classmethod by value (cloudpickle), and the test run's
    # type-check wrapper (jaxtyping's import hook) holds weakrefs, which do not pickle.
    @classmethod
    @no_type_check
    def create(cls, subject: Subject, settings: ShardSettings) -> "ShardBuilder":
        with single_thread_torch():
            template = build_template(subject.template, dtype=torch.float64)
            if bool((template.face_uvs < 0).any()):
                raise ValueError(f"{subject.template.files.get('mesh', subject.template.kind)}: the template has no "
                                 f"per-corner uvs (vt); needed for normal maps")
            for seq in subject.sequences.values():
                if seq.poses is not None and seq.poses.dofs.shape[1] != template.num_dofs:
                    raise ValueError(f"{seq.name}: the pose parameters have {seq.poses.dofs.shape[1]} values per "
                                     f"frame, the {subject.template.kind} template takes {template.num_dofs}")
            faces = template.faces.numpy()
            offsets = _outer_offsets(template, subject.template.files.get("outer"), settings.offset_mm)
            atlas = UVAtlas(template.uvs.numpy(), template.face_uvs.numpy())
            table = uv_texel_table(atlas, settings.atlas_res, settings.gutter)
            geometry = FrameGeometryBuilder(faces, offsets, table, dtype=torch.float16)
            meshes = {k: read_meshes(s.surfaces, template.num_verts) for k, s in subject.sequences.items()
                      if s.surfaces is not None}
        return cls(subject, settings, template, offsets, table, geometry, meshes)

    def shard_geometry(self, sequence: str, frames: Sequence[int]) -> ShardGeometry:
        """Pose parameters, inner/outer surfaces and normal maps of ``frames`` of ``sequence``."""
        frames = np.asarray(frames, np.int64)
        poses = self.subject.sequences[sequence].poses
        if poses is not None:
            try:
                rows = np.array([poses.row_of(int(f)) for f in frames])
            except KeyError as err:
                raise ValueError(f"{sequence}: motion lacks a frame of the temporal window ({err.args[0]})") from None
            dofs = poses.dofs[rows]
        else:
            dofs = np.zeros((len(frames), self.template.num_dofs))
        seq_meshes = self.meshes.get(sequence)
        with single_thread_torch():
            if seq_meshes is not None:
                index = {int(f): i for i, f in enumerate(seq_meshes.frames)}
                missing = [int(f) for f in frames if int(f) not in index]
                if missing:
                    raise ValueError(f"{sequence}: .meshes lacks frame {missing[0]} (needed by the temporal window)")
                inner = seq_meshes.verts[[index[int(f)] for f in frames]].astype(np.float64)
            else:
                with torch.no_grad():
                    inner = self.template.pose(torch.as_tensor(dofs, dtype=torch.float64)).numpy()
            geo = self.geometry.build(inner)
        return ShardGeometry(frames, dofs, geo.inner, geo.outer, geo.normal_maps_inner.numpy(),
                             geo.normal_maps_outer.numpy())

    def _kept_source(self, sequence: str) -> FrameSource:
        """The sequence's frame source, opened on first use and kept for the builder's life (several threads of a
        worker may share the builder)."""
        with _OPEN_SOURCES_LOCK:
            src = self.open_sources.get(sequence)
            if src is None:
                src = self.open_sources[sequence] = self.subject.sequences[sequence].images.open()
            return src

    def close(self) -> None:
        """Close the frame sources kept open across shards (a builder living as long as its worker process needs
        no call: the files are read-only)."""
        with _OPEN_SOURCES_LOCK:
            sources = list(self.open_sources.values())
            self.open_sources.clear()
        for src in sources:
            src.close()

    def write(self, task: ShardTask) -> dict:
        """Write one shard atomically; returns its manifest entry."""
        t0 = time.perf_counter()
        geo = self.shard_geometry(task.sequence, task.geometry_frames)
        seq = self.subject.sequences[task.sequence]
        s = self.settings
        kept = getattr(seq.images, "keep_open", False)
        src = self._kept_source(task.sequence) if kept else seq.images.open()
        writer = ShardWriter(s.out_dir / task.name, task.sequence, task.frames, s.cameras, seq.height, seq.width,
                             Codec.parse(s.codec), geo, s.window, seq.first_frame)
        try:
            for col, cam in enumerate(s.cameras):  # camera-major: each video is decoded forward once
                for row, frame in enumerate(task.frames):
                    rgb, mask = src.read(frame, cam)
                    writer.put(row, col, rgb, mask)
            sha, size = writer.commit()
        except BaseException:
            writer.abort()
            raise
        finally:
            if not kept:
                src.close()
        return {"name": task.name, "sequence": task.sequence, "frames": list(task.frames), "sha256": sha,
                "bytes": size, "seconds": time.perf_counter() - t0}

