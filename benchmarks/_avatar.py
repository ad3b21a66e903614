"""Inputs shared by the speed benchmarks: the posed character, its cameras and ray sets, the paper model.

The DDC sample (``../shared/dynacap-sample``) posed at one frame of its motion; when the sample
is absent, the procedural character (``deliffas.geometry.procedural``) in a temporary folder.
Cameras are pinholes 3 m in front of the posed body looking at its bounding-box centre,
fx = fy = 0.9 x W (the person is then ~70 % of the image height at 940 rows). Smoke mode: 32^2 and 64 x 96
images, the paper model at atlas side 64.
"""

from __future__ import annotations

import dataclasses
import functools
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import SAMPLE_DIR, sized

SHELL_OFFSET_MM = 30.0
"""Outer surface offset, as DELIFFAS."""
CAMERA_DISTANCE_MM = 3000.0
FOCAL_PER_WIDTH = 0.9
SIZES = {"256^2": (256, 256), "940x1285": (1285, 940)}
"""Image sizes (W, H): a square 256^2 and the DynaCap frame (W x H = 1285 x 940)."""
SMOKE_SIZES = {"32^2": (32, 32), "64x96": (96, 64)}
"""Image sizes (W, H) in smoke mode."""
SMOKE_ATLAS = 64
"""Atlas side of the paper model in smoke mode."""
POSE_FRAME = 500


class Unavailable(RuntimeError):
    """Neither the DDC sample nor the procedural character can be loaded."""


@dataclass(frozen=True)
class Avatar:
    """One posed frame of a character.

    Attributes:
        source: "DDC sample" or "procedural".
        inner: (V, 3) float32, mm, the posed mesh.
        outer: (V, 3) float32, mm, the 30 mm offset shell.
        faces: (F, 3) int64.
        atlas: UVAtlas of the template (per-corner uvs).
        normals_seq: (K, V, 3) float32 unit vertex normals of K consecutive frames (for normal maps).
    """

    source: str
    inner: np.ndarray
    outer: np.ndarray
    faces: np.ndarray
    atlas: object
    normals_seq: torch.Tensor


def _character_path() -> tuple[Path, str]:
    if (SAMPLE_DIR / "ddc.character").is_file():
        return SAMPLE_DIR / "ddc.character", "DDC sample"
    try:
        from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character
    except ImportError as exc:
        raise Unavailable(f"DDC sample absent and no procedural character ({exc})") from exc
    out = Path(tempfile.mkdtemp(prefix="deliffas_bench_"))
    return Path(make_procedural_character(ProceduralConfig(out))), "procedural"


@functools.lru_cache(maxsize=1)
def avatar(num_normal_frames: int = 8) -> Avatar:
    """The posed character (cached per process)."""
    from deliffas.io.formats.dynacap.character import read_character, read_motion
    from deliffas.geometry.atlas import UVAtlas
    from deliffas.geometry.mesh_ops import vertex_normals
    from deliffas.geometry.shell import offset_shell
    from deliffas.geometry.templates import DDCTemplate

    path, source = _character_path()
    character = read_character(path)
    template = DDCTemplate(character)
    motion_path = character.files.dof_file
    dofs = None
    for candidate in (SAMPLE_DIR / "skeletoolToGTPose" / "poseAngles.motion", motion_path):
        if source == "DDC sample" and candidate is not None and Path(candidate).is_file():
            dofs = read_motion(candidate, character.skeleton.num_dofs).dofs
            break
    if dofs is None:  # procedural: its own motion file if any, else the rest pose
        motions = sorted(path.parent.glob("*.motion"))
        dofs = read_motion(motions[0], character.skeleton.num_dofs).dofs if motions else character.rest_dofs[None]
    start = min(POSE_FRAME, len(dofs) - 1)
    window = np.asarray(dofs[max(0, start - num_normal_frames + 1): start + 1])
    with torch.no_grad():
        verts = template.pose(torch.tensor(window, dtype=torch.float32))  # (K, V, 3)
    faces = np.asarray(character.mesh.faces, np.int64)
    normals = vertex_normals(verts, torch.from_numpy(faces))
    inner = verts[-1].numpy().astype(np.float32)
    outer = np.asarray(offset_shell(inner, faces, SHELL_OFFSET_MM), np.float32)
    atlas = UVAtlas(character.mesh.uvs, character.mesh.face_uvs)
    return Avatar(source, inner, outer, faces, atlas, normals.float())


def look_at(center: np.ndarray, target: np.ndarray, width: int, height: int, focal: float):
    """A pinhole ``Camera`` at ``center`` looking at ``target``, y-up world (image y down)."""
    from deliffas.io.cameras import Camera, look_at as world_to_cam

    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return Camera(f"bench_{width}x{height}", K, world_to_cam(center, target), width, height)


def sizes() -> dict[str, tuple[int, int]]:
    """The image sizes of this mode: :data:`SIZES`, or :data:`SMOKE_SIZES` in smoke mode."""
    return sized(SIZES, SMOKE_SIZES)


def camera(av: Avatar, size: str):
    """The benchmark camera of ``size`` (a key of :func:`sizes`) in front of the posed body."""
    width, height = sizes()[size]
    lo, hi = av.outer.min(0).astype(np.float64), av.outer.max(0).astype(np.float64)
    target = (lo + hi) / 2
    center = target + np.array([0.0, 0.0, CAMERA_DISTANCE_MM])
    return look_at(center, target, width, height, FOCAL_PER_WIDTH * width)


def skipped(group: str, reason: str):
    from benchmarks.common import Result

    return [Result(group, f"skipped: {reason}", 0.0, "")]


def avatar_run(group: str, body):
    """``body(avatar())`` with ``BENCH_THREADS`` torch threads, or a "skipped" row of ``group``
    when neither the DDC sample nor the procedural character is available."""
    from benchmarks._timing import torch_threads

    with torch_threads():
        try:
            av = avatar()
        except Unavailable as exc:
            return skipped(group, str(exc))
        return body(av)


@functools.lru_cache(maxsize=None)
def rays(size: str):
    """``deliffas.engine.rays.CameraRays`` of the benchmark camera of ``size`` (cached)."""
    from deliffas.engine.rays import camera_rays
    from deliffas.geometry.raycast import UVRaycaster

    av = avatar()
    return camera_rays(UVRaycaster(av.inner, av.faces, av.outer, av.atlas), camera(av, size))


def paper_model():
    """``DeliffasModel`` of ``two_surface`` at the ``paper`` preset, eval mode, seed 0 (cached); at atlas side
    :data:`SMOKE_ATLAS` in smoke mode."""
    return _paper_model(sized(None, SMOKE_ATLAS))


@functools.lru_cache(maxsize=None)
def _paper_model(atlas_res: int | None):
    """The paper model at atlas side ``atlas_res`` (None: the preset's 1024)."""
    from deliffas.models import DeliffasModel, get_config

    cfg = get_config("two_surface", "paper")
    torch.manual_seed(0)
    return DeliffasModel(cfg if atlas_res is None else dataclasses.replace(cfg, atlas_res=atlas_res)).eval()


def random_features(model, seed: int = 0):
    """``FrameFeatures`` of one frame with uniform [0, 1) maps of the model's size, channels_last
    (as ``DeliffasModel.encode`` stores them); stands in for the per-frame U-Net output."""
    from deliffas.models.deliffas import FrameFeatures

    cfg = model.config
    gen = torch.Generator().manual_seed(seed)
    shape = (1, cfg.feature_channels, cfg.atlas_res, cfg.atlas_res)
    maps = [torch.rand(shape, generator=gen).contiguous(memory_format=torch.channels_last) for _ in range(2)]
    return FrameFeatures(inner=maps[0], outer=maps[1] if model.spec.outer_unet else None)


def ray_query(r):
    """The two-surface ``RayQuery`` of a ``CameraRays`` (batch index 0)."""
    from deliffas.models.ray_query import RayQuery

    return RayQuery(batch_index=torch.zeros(r.num_rays, dtype=torch.long), uv_inner=torch.from_numpy(r.uv_inner),
                    uv_outer=torch.from_numpy(r.uv_outer), inner_from_outer=torch.from_numpy(r.inner_from_outer))
