"""Synthetic multi-view DynaCap captures whose ground truth holds what the skinned template lacks.

``synthesize_capture(out_dir, SynthConfig)`` writes a subject folder in DynaCap layout (docs/data.md):
a camera dome, the body (a DDC character, or an SMPL model with ``body_model``,
:mod:`deliffas.data.synth_body`), a training and a novel-pose testing motion, per-frame RGBA images (and
on request FFV1 videos), and the ground-truth surfaces as ``.meshes``. The ground truth is the skinned
template plus

(a) a loose garment: the skirt region (segmentation label 12; for characters without it a lower
    torso / upper leg band) pushed outward by 2-6 cm, more towards the hem, with the leg spread (pose)
    and with the lagged velocity of the region (more on the trailing side), smoothed over the surface;
(b) view-dependent shading: Blinn-Phong specular from a fixed directional light;
(c) pose-dependent shading: per-frame ambient occlusion of the posed geometry and wrinkle bands on the
    garment whose phase follows the leg spread.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.cameras import Camera, look_at
from deliffas.io.formats.dynacap.meshes import MeshSequence, write_meshes
from deliffas.io.formats.dynacap.calibration import write_calibration
from deliffas.io.infra.files import claim_output
from deliffas.io.formats.dynacap.frames import ImageFolderSource, VideoWriterSet, write_image
from deliffas.io.infra.text_lines import write_text_atomic
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.templates import build_template
from deliffas.data.garment import GarmentFrames, garment_deformation, region_weights
from deliffas.data.render_gt import ShadingConfig, camera_rays, render_views, vertex_ambient_occlusion
from deliffas.data.synth_body import make_synth_body
from deliffas.data.synth_config import IMAGES_KEY, STRAIGHT_IMAGES, SynthConfig
from deliffas.parallel import process_map

__all__ = [
    "SynthConfig",
    "SynthResult",
    "synthesize_capture",
    "dome_cameras",
    "choose_test_cameras",
    "SEQUENCES",
]

log = logging.getLogger(__name__)

SEQUENCES = ("training", "testing")
"""Sequence folders of a subject: training motion and novel-pose testing motion."""


@dataclass(frozen=True)
class SynthResult:
    """Paths and facts of a synthesized subject."""
    out_dir: Path
    body: Path
    """The body's main file in the subject: ``character/<name>.character`` or ``body/<model>.npz``."""
    calibration: Path
    cameras: list[Camera]
    train_cameras: list[int]
    test_cameras: list[int]
    frames: dict[str, list[int]]
    seconds: dict[str, float]


# --------------------------------------------------------------------------------------------- cameras
def dome_cameras(center: np.ndarray, radius: float, num: int, width: int, height: int, seed: int = 0,
                 distance_mm: tuple[float, float] = (3000.0, 4000.0),
                 elevation_deg: tuple[float, float] = (-5.0, 35.0)) -> list[Camera]:
    """Cameras on a dome around ``center`` looking at it, each framing a sphere of ``radius``.

    Azimuths are evenly spaced with a seeded jitter, elevations and distances vary per camera (a
    golden-ratio sequence over the ranges plus jitter). Principal point at the image centre
    (W/2, H/2) in the pixel-corner convention; square pixels.

    Returns:
        ``num`` cameras named "0" .. "num-1", world y-up, mm.
    """
    rng = np.random.default_rng(seed)
    center = np.asarray(center, np.float64)
    cams = []
    for k in range(num):  # a handful of cameras
        az = 2 * np.pi * (k + rng.uniform(-0.2, 0.2)) / num
        u = (k * 0.6180339887 + rng.uniform(-0.1, 0.1)) % 1.0
        el = np.deg2rad(elevation_deg[0] + u * (elevation_deg[1] - elevation_deg[0]))
        dist = rng.uniform(*distance_mm)
        eye = center + dist * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
        E = look_at(eye, center)
        half = np.arcsin(min(radius / dist, 0.95))
        f = 0.5 * min(width, height) * 0.95 / np.tan(half)
        K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
        cams.append(Camera(str(k), K, E, int(width), int(height), (36.0, 36.0 * height / width)))
    return cams


def choose_test_cameras(num_cameras: int, spec: int | Sequence[int] | None) -> list[int]:
    """Held-out camera indices: ``spec`` = count (spread evenly), explicit indices, or None (max(1, C // 8))."""
    if spec is None:
        spec = max(1, num_cameras // 8) if num_cameras > 1 else 0
    if isinstance(spec, (int, np.integer)):
        n = int(spec)
        if not 0 <= n < num_cameras:
            raise ValueError(f"test cameras: need 0 <= N < {num_cameras} cameras, got {n}")
        return sorted({int((k + 0.5) * num_cameras / n) for k in range(n)}) if n else []
    out = sorted({int(c) for c in spec})
    if out and (out[0] < 0 or out[-1] >= num_cameras):
        raise ValueError(f"test cameras {out}: indices must be in [0, {num_cameras})")
    if len(out) >= num_cameras:
        raise ValueError("test cameras: at least one camera must remain for training")
    return out


# --------------------------------------------------------------------------------------------- rendering workers
_WORKER: dict = {}


def _init_worker(static: dict) -> None:

    _WORKER.clear()
    _WORKER.update(static)
    _WORKER["rays"] = [camera_rays(c, static["shading"].supersample) for c in static["cameras"]]


def _render_chunk(seq: str, rows: list[int]) -> int:
    """AO + render + write the images of rows ``rows`` of sequence ``seq`` (every camera).

    Tasks are tiny (the geometry travels once per worker in the initializer's ``static``): a worker
    that dies then never leaves the pool's task pipe half-written.
    """
    s = _WORKER
    data = s["sequences"][seq]
    for i in rows:  # frames of this chunk
        verts, frame = data["verts"][i], int(data["frames"][i])
        normals = vertex_normals(verts, s["faces"])
        ao = vertex_ambient_occlusion(verts, s["faces"], normals, s["ao_rays"], seed=data["ao_seed"] + frame)
        views = render_views(verts, s["faces"], s["uvs"], s["face_uvs"], s["texture"], s["cameras"],
                             ao, data["albedo"][i], s["shading"], normals=normals, rays=s["rays"])
        for c, view in enumerate(views):
            write_image(data["root"], frame, c, view.rgb, view.alpha)
    return len(rows)


def _chunks(n: int, parts: int) -> list[np.ndarray]:
    return [c for c in np.array_split(np.arange(n), max(1, min(parts, n))) if len(c)]


# --------------------------------------------------------------------------------------------- main entry
def synthesize_capture(out_dir: str | os.PathLike, config: SynthConfig = SynthConfig()) -> SynthResult:
    """Write a synthetic DynaCap subject folder (layout in docs/data.md) and return what was written."""
    import torch

    if config.num_frames < 1 or config.num_cameras < 2:
        raise ValueError(f"synth needs >= 1 frame and >= 2 cameras, got {config.num_frames} and {config.num_cameras}")
    out = claim_output(out_dir, config.overwrite, "synth.json", "a synthetic capture")
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    body = make_synth_body(out, config.seed, config.character, config.body_model, config.body_uv, config.skinning)
    num_test = config.num_test_frames if config.num_test_frames is not None else max(1, config.num_frames // 2)
    motions = {
        "training": body.motion(config.motion, config.num_frames, config.seed, config.fps),
        "testing": body.motion(config.test_motion, num_test, config.seed + 1000, config.fps),
    }
    template = build_template(body.spec, dtype=torch.float64)
    weights = region_weights(body.garment, body.faces)
    faces = body.faces
    gt: dict[str, np.ndarray] = {}
    garment: dict[str, GarmentFrames] = {}
    for seq, motion in motions.items():
        with torch.no_grad():
            posed = template.pose(torch.as_tensor(motion.dofs)).numpy()
        garment[seq] = garment_deformation(posed, faces, body.rest_verts, weights, config.fps,
                                           config.garment_min_mm, config.garment_max_mm)
        gt[seq] = posed + garment[seq].offsets
    seconds["geometry"] = time.perf_counter() - t0

    allv = np.concatenate([v.reshape(-1, 3) for v in gt.values()])
    center = 0.5 * (allv.min(axis=0) + allv.max(axis=0))
    radius = float(np.linalg.norm(allv - center, axis=1).max())
    cameras = dome_cameras(center, radius, config.num_cameras, config.width, config.height, config.seed,
                           config.camera_distance_mm, config.camera_elevation_deg)
    test_cams = choose_test_cameras(config.num_cameras, config.test_cameras)
    train_cams = [c for c in range(config.num_cameras) if c not in test_cams]
    calib = out / "cameras.calibration"
    write_calibration(calib, cameras)
    frames = {seq: [int(f) for f in m.frames] for seq, m in motions.items()}
    _write_split(out, cameras, train_cams, test_cams, frames)

    for seq in SEQUENCES:
        seq_dir = out / seq
        seq_dir.mkdir(exist_ok=True)
        body.write_motion(seq_dir, motions[seq], config.fps)
        write_meshes(seq_dir / "gt.meshes", MeshSequence(motions[seq].frames, gt[seq].astype(np.float32)))

    t2 = time.perf_counter()
    static = {
        "faces": faces,
        "uvs": body.uvs,
        "face_uvs": body.face_uvs,
        "texture": body.texture,
        "cameras": cameras,
        "ao_rays": config.ao_rays,
        "shading": ShadingConfig(**{**asdict(config.shading), "supersample": config.supersample}),
    }
    static["sequences"] = {
        seq: {"root": str(out / seq / f"rgb_{config.width}_{config.height}"), "frames": np.asarray(frames[seq]),
              "verts": gt[seq], "albedo": garment[seq].albedo_scale, "ao_seed": config.seed * 1_000_003 + k * 100_003}
        for k, seq in enumerate(SEQUENCES)}
    tasks = [(seq, [int(i) for i in idx]) for seq in SEQUENCES
             for idx in _chunks(len(frames[seq]), 2 * max(1, config.jobs))]
    _render_tasks(static, tasks, config.jobs)
    seconds["render"] = time.perf_counter() - t2  # ambient occlusion + ray casting + PNG writing

    if config.videos:
        t3 = time.perf_counter()
        _write_videos(out, [c.name for c in cameras], frames, config)
        seconds["videos"] = time.perf_counter() - t3

    record = {"config": _jsonable(asdict(config)), IMAGES_KEY: STRAIGHT_IMAGES,
              "body": {"kind": body.kind, "path": str(body.path.relative_to(out))},
              "garment": {seq: {"max_offset_mm": float(np.linalg.norm(g.offsets, axis=-1).max()),
                                "spread_mm": [round(float(x), 3) for x in g.spread_mm],
                                "speed_mm_s": [round(float(x), 3) for x in g.speed_mm_s]}
                          for seq, g in garment.items()}}
    write_text_atomic(out / "synth.json", json.dumps(record, indent=2) + "\n")  # last: marks a finished capture
    seconds["total"] = time.perf_counter() - t0
    log.info("synth %s: %s", out, {k: round(v, 2) for k, v in seconds.items()})
    return SynthResult(out, body.path, calib, cameras, train_cams, test_cams, frames, seconds)


def _write_split(out: Path, cameras: list[Camera], train_cams: list[int], test_cams: list[int],
                 frames: dict[str, list[int]]) -> None:
    """``split.json`` (camera names and split, frame ranges, the protocol's frame step) and ``test_cameras.txt``."""
    split = {
        "camera_names": [c.name for c in cameras],
        "train_cameras": train_cams,
        "test_cameras": test_cams,
        "sequences": {seq: {"frames": [frames[seq][0], frames[seq][-1] + 1]} for seq in SEQUENCES},
        "protocol_frame_step": 10,
    }
    write_text_atomic(out / "split.json", json.dumps(split, indent=2) + "\n")
    write_text_atomic(out / "test_cameras.txt", "".join(f"{c}\n" for c in test_cams))


def _render_tasks(static: dict, tasks: list[tuple[str, list[int]]], jobs: int) -> None:
    """Render every (sequence, frame indices) task: in this process, or in ``jobs`` worker processes."""
    if jobs <= 1:
        _init_worker(static)
        for task in tasks:
            _render_chunk(*task)
        _WORKER.clear()
        return
    for _ in process_map(_render_chunk, tasks, min(jobs, len(tasks)), _init_worker, (static,)):
        pass


def _write_videos(out: Path, names: list[str], frames: dict[str, list[int]], config: SynthConfig) -> None:
    """One video per camera and sequence from the rendered PNG frames (``SynthConfig.videos``)."""
    for seq in SEQUENCES:
        src = ImageFolderSource(out / seq)
        writers = VideoWriterSet(out / seq, names, config.width, config.height, config.fps)
        try:
            for f in frames[seq]:
                for c in range(len(names)):
                    writers.write(c, *src.read(f, c))
        finally:
            writers.close()


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    return x
