"""Synthetic multi-view DynaCap captures whose ground truth holds what the skinned template lacks.

``synthesize_capture(out_dir, SynthConfig)`` writes a subject folder in DynaCap layout (docs/data.md):
a camera dome, the character, a training and a novel-pose testing motion, per-frame RGBA images (and
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
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from deliffas.io.cameras import Camera, look_at
from deliffas.io.dynacap import Character, Motion, read_character, read_motion, write_character, write_motion
from deliffas.io.meshes import MeshSequence, write_meshes
from deliffas.io.calibration import write_calibration
from deliffas.io.frames import ImageFolderSource, VideoWriterSet, write_image
from deliffas.io.text_lines import write_text_atomic
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.motion_gen import procedural_motion
from deliffas.geometry.procedural import make_procedural_character
from deliffas.geometry.templates import build_template, ddc_spec
from deliffas.data.render_gt import ShadingConfig, camera_rays, render_views, vertex_ambient_occlusion
from deliffas.parallel import process_map

__all__ = [
    "SynthConfig",
    "SynthResult",
    "synthesize_capture",
    "garment_weights",
    "garment_deformation",
    "GarmentFrames",
    "dome_cameras",
    "choose_test_cameras",
    "GARMENT_LABEL",
    "SEQUENCES",
]

log = logging.getLogger(__name__)

GARMENT_LABEL = 12
"""Segmentation label of the loose garment (skirt) of the procedural character."""
SEQUENCES = ("training", "testing")
"""Sequence folders of a subject: training motion and novel-pose testing motion."""
_BAND = (0.30, 0.57)
"""Fallback garment region: rest-pose height band (fraction of the mesh height) for characters without label 12."""
_NOT_GARMENT_BONES = ("Arm", "Hand", "Shoulder", "Head", "Neck")


@dataclass(frozen=True)
class SynthConfig:
    """What ``synthesize_capture`` renders."""
    num_frames: int = 20
    """Frames of the training sequence (0 .. N-1)."""
    num_test_frames: int | None = None
    """Frames of the novel-pose testing sequence (default: max(1, num_frames // 2))."""
    num_cameras: int = 8
    """Cameras of the dome."""
    width: int = 256
    """Image width in pixels."""
    height: int = 256
    """Image height in pixels."""
    test_cameras: int | tuple[int, ...] | None = None
    """Held-out cameras: a count N (spread evenly) or explicit indices; None = max(1, C // 8)."""
    seed: int = 0
    """Seeds the character, the motions, the camera dome and the AO sampling."""
    character: str | None = None
    """A ``.character`` to use instead of the procedural character (copied into the subject)."""
    motion: str | None = None
    """Training motion file instead of the procedural motion (its first ``num_frames`` frames)."""
    test_motion: str | None = None
    """Testing motion file instead of a procedural one with another seed."""
    videos: bool = False
    """Also write per-camera FFV1 videos ``<seq>/img/c_<name>.avi`` + ``<seq>/fg/c_<name>.avi``."""
    jobs: int = 1
    """Rendering processes (frames are split between them)."""
    fps: float = 25.0
    """Frame rate: velocities of the garment model and of the videos."""
    supersample: int = 1
    """s x s rays per pixel (anti-aliased coverage alpha)."""
    garment_min_mm: float = 20.0
    """Smallest outward displacement inside the garment region."""
    garment_max_mm: float = 60.0
    """Largest outward displacement."""
    skinning: Literal["dqs", "lbs"] = "dqs"
    """Skinning of the template the garment is added to."""
    camera_distance_mm: tuple[float, float] = (3000.0, 4000.0)
    """Range of camera distances from the subject centre."""
    camera_elevation_deg: tuple[float, float] = (-5.0, 35.0)
    """Range of camera elevations."""
    ao_rays: int = 16
    """Hemisphere rays per vertex of the ambient-occlusion proxy."""
    shading: ShadingConfig = field(default_factory=ShadingConfig)
    """Light and material."""


@dataclass(frozen=True)
class SynthResult:
    """Paths and facts of a synthesized subject."""
    out_dir: Path
    character: Path
    calibration: Path
    cameras: list[Camera]
    train_cameras: list[int]
    test_cameras: list[int]
    frames: dict[str, list[int]]
    seconds: dict[str, float]


# --------------------------------------------------------------------------------------------- garment
def _vertex_smoother(faces: np.ndarray, num_verts: int):
    """(V, V) sparse row-stochastic matrix: x <- mean of x over the vertex and its neighbours."""
    import scipy.sparse as sp

    f = np.asarray(faces, np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0], np.arange(num_verts)])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2], np.arange(num_verts)])
    A = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(num_verts, num_verts))
    A.data[:] = 1.0  # duplicate edges count once
    deg = np.asarray(A.sum(axis=1)).ravel()
    return sp.diags(1.0 / np.maximum(deg, 1)) @ A


def _smooth(values: np.ndarray, smoother, iterations: int) -> np.ndarray:
    """Apply the smoother to (V,) or (V, K) or (N, V, K) values ``iterations`` times."""
    x = values
    for _ in range(iterations):
        if x.ndim == 3:
            n, v, k = x.shape
            x = (smoother @ x.transpose(1, 0, 2).reshape(v, n * k)).reshape(v, n, k).transpose(1, 0, 2)
        else:
            x = smoother @ x
    return np.asarray(x)


def garment_weights(character: Character, smooth_iterations: int = 4) -> np.ndarray:
    """Per-vertex garment weight in [0, 1]: 1 on the loose region, fading over a few rings outside it.

    The region is segmentation label ``GARMENT_LABEL`` (12, the procedural character's skirt); for
    characters without it (e.g. the DDC sample), the rest-pose height band ``_BAND`` of the mesh
    (lower torso and upper legs) minus vertices dominated by arm, hand, head or neck bones.
    """
    mesh = character.mesh
    seg = character.segmentation
    if seg is not None and np.any(seg == GARMENT_LABEL):
        core = seg == GARMENT_LABEL
    else:
        y = mesh.verts[:, 1]
        lo, hi = y.min(), y.max()
        h = (y - lo) / max(hi - lo, 1e-9)
        core = (h >= _BAND[0]) & (h <= _BAND[1])
        skin = character.skin
        dominant = skin.indices[np.arange(skin.num_verts), np.argmax(skin.weights, axis=1)]
        bad = np.array([any(k in b for k in _NOT_GARMENT_BONES) for b in skin.bones])
        core &= ~bad[dominant]
    smoother = _vertex_smoother(mesh.faces, mesh.num_verts)
    w = _smooth(core.astype(np.float64), smoother, smooth_iterations)
    return np.maximum(w / max(w.max(), 1e-12), core.astype(np.float64)).clip(0.0, 1.0)


@dataclass(frozen=True)
class GarmentFrames:
    """The garment model of one sequence.

    Attributes:
        offsets: (N, V, 3) float64 mm, ground truth minus skinned template.
        albedo_scale: (N, V) float64 wrinkle-band multiplier of the albedo.
        spread_mm: (N,) leg spread of the region relative to the rest pose (the pose input).
        speed_mm_s: (N,) mean lagged speed of the region (the velocity input).
    """
    offsets: np.ndarray
    albedo_scale: np.ndarray
    spread_mm: np.ndarray
    speed_mm_s: np.ndarray


def garment_deformation(posed: np.ndarray, faces: np.ndarray, rest_verts: np.ndarray, weights: np.ndarray,
                        fps: float = 25.0, min_mm: float = 20.0, max_mm: float = 60.0,
                        lag: float = 0.7) -> GarmentFrames:
    """Pose- and velocity-dependent outward displacement of the garment region (beyond the template).

    Per vertex i and frame f (w_i the garment weight, h_i in [0, 1] from the waist to the hem in the
    rest pose):

        d_if = w_i * smooth(clip(min + 14 h_i + pose_f + vel_if, min, max))  [mm]
        pose_f = 15 * clip(spread_f / 80, -0.5, 1)                   (leg spread vs. rest, mm)
        vel_if = 20 * clip(|u_if| / 1000, 0, 1) * (0.4 + 0.6 * trailing_if)

    where u is the template's vertex velocity (mm/s) low-passed over time (``lag``) and over the
    surface, and trailing = max(0, -dir . u/|u|) (cloth lags behind the motion). The direction is the
    vertex normal blended with the horizontal radial direction from the region's centre (a flare);
    smooth() averages over 3 rings of the surface before the (smooth) weight is applied.

    Args:
        posed: (N, V, 3) skinned template vertices of consecutive frames, mm.
        faces: (F, 3).
        rest_verts: (V, 3) template in its rest pose.
        weights: (V,) garment weights from ``garment_weights``.
    """
    num_frames, num_verts = posed.shape[:2]
    smoother = _vertex_smoother(faces, num_verts)
    w = np.asarray(weights, np.float64)
    core = w > 0.5
    y = rest_verts[:, 1]
    y_top, y_bot = y[core].max(), y[core].min()
    hem = np.clip((y_top - y) / max(y_top - y_bot, 1e-9), 0.0, 1.0)
    wn = w / w.sum()
    normals = vertex_normals(posed, faces)  # (N, V, 3)
    centre = np.einsum("v,nvc->nc", wn, posed)  # (N, 3)
    radial = posed - centre[:, None]
    radial[..., 1] = 0.0
    radial /= np.maximum(np.linalg.norm(radial, axis=-1, keepdims=True), 1e-9)
    direction = normals + radial
    direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-9)
    lower = core & (hem > 0.5)

    def spread(v: np.ndarray) -> np.ndarray:  # (..., V, 3) -> (...) RMS horizontal radius of the lower region
        c = v[..., lower, :].mean(axis=-2, keepdims=True)
        d = v[..., lower, :] - c
        return np.sqrt((d[..., 0] ** 2 + d[..., 2] ** 2).mean(axis=-1))

    spread_mm = spread(posed) - spread(rest_verts)
    pose_term = 15.0 * np.clip(spread_mm / 80.0, -0.5, 1.0)  # (N,)
    vel = np.diff(posed, axis=0, prepend=posed[:1]) * fps  # (N, V, 3) mm/s
    lagged = np.empty_like(vel)
    acc = np.zeros_like(vel[0])
    for f in range(num_frames):  # a recursion over time (frames), vectorised over vertices
        acc = lag * acc + (1.0 - lag) * vel[f]
        lagged[f] = acc
    lagged = _smooth(lagged, smoother, 3)
    speed = np.linalg.norm(lagged, axis=-1)  # (N, V)
    trailing = np.clip(-np.einsum("nvc,nvc->nv", direction, lagged) / np.maximum(speed, 1e-9), 0.0, 1.0)
    vel_term = 20.0 * np.clip(speed / 1000.0, 0.0, 1.0) * (0.4 + 0.6 * trailing)
    mag = np.clip(min_mm + 14.0 * hem[None] + pose_term[:, None] + vel_term, min_mm, max_mm)
    mag = _smooth(mag.T, smoother, 3).T * w[None]  # (N, V); exactly 0 where w = 0
    offsets = mag[..., None] * direction
    phase = 2 * np.pi * spread_mm / 120.0
    bands = 0.5 + 0.5 * np.cos(2 * np.pi * 4.0 * hem[None] + phase[:, None])
    albedo_scale = 1.0 - 0.22 * w[None] * bands
    speed_mean = (speed * wn[None]).sum(axis=1)
    return GarmentFrames(offsets, albedo_scale, spread_mm, speed_mean)


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


# --------------------------------------------------------------------------------------------- character & motion
def _default_character(out_dir: Path, seed: int) -> Path:
    """The project's procedural character (the demo's default; no sample data needed)."""
    return Path(make_procedural_character(out_dir / "character", seed))


def _copy_character(path: Path, out_dir: Path) -> Path:
    character = read_character(path)
    return write_character(out_dir / "character", character, name=Path(path).stem)


def _make_motion(character: Character, path: str | None, num_frames: int, seed: int, fps: float) -> Motion:
    if path is not None:
        m = read_motion(path, num_dofs=character.skeleton.num_dofs)
        if m.num_frames < num_frames:
            raise ValueError(f"{path}: has {m.num_frames} frames, {num_frames} requested")
        return Motion(np.arange(num_frames, dtype=np.int64), m.dofs[:num_frames].copy())
    m = procedural_motion(character.skeleton, num_frames, seed, style="mixed", rest_dofs=character.rest_dofs, fps=fps)
    return Motion(np.arange(m.num_frames, dtype=np.int64), np.asarray(m.dofs, np.float64))


def _load_texture(character: Character, seed: int) -> np.ndarray:
    """(Ht, Wt, 3) float32 texture of the character, or a seeded procedural one when it has none."""
    import cv2

    if character.texture is not None:
        img = cv2.imread(str(character.texture), cv2.IMREAD_COLOR)
        if img is not None:
            return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    rng = np.random.default_rng(seed)
    size = 256
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = rng.uniform(0.3, 0.8, 3)
    checker = ((np.floor(xx * 16) + np.floor(yy * 16)) % 2)[..., None]
    noise = cv2.GaussianBlur(rng.uniform(0, 1, (size, size, 3)).astype(np.float32), (0, 0), 3)
    return np.clip(base * (0.75 + 0.25 * checker) + 0.3 * (noise - 0.5), 0, 1).astype(np.float32)


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
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    char_path = _copy_character(Path(config.character), out) if config.character else _default_character(out, config.seed)
    character = read_character(char_path)
    num_test = config.num_test_frames if config.num_test_frames is not None else max(1, config.num_frames // 2)
    motions = {
        "training": _make_motion(character, config.motion, config.num_frames, config.seed, config.fps),
        "testing": _make_motion(character, config.test_motion, num_test, config.seed + 1000, config.fps),
    }
    template = build_template(ddc_spec(char_path, config.skinning), dtype=torch.float64)
    weights = garment_weights(character)
    faces = np.asarray(character.mesh.faces, np.int64)
    gt: dict[str, np.ndarray] = {}
    garment: dict[str, GarmentFrames] = {}
    for seq, motion in motions.items():
        with torch.no_grad():
            posed = template.pose(torch.as_tensor(motion.dofs)).numpy()
        garment[seq] = garment_deformation(posed, faces, character.mesh.verts, weights, config.fps,
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
    split = {
        "camera_names": [c.name for c in cameras],
        "train_cameras": train_cams,
        "test_cameras": test_cams,
        "sequences": {seq: {"frames": [frames[seq][0], frames[seq][-1] + 1]} for seq in SEQUENCES},
        "protocol_frame_step": 10,
    }
    write_text_atomic(out / "split.json", json.dumps(split, indent=2) + "\n")
    write_text_atomic(out / "test_cameras.txt", "".join(f"{c}\n" for c in test_cams))

    for seq in SEQUENCES:
        seq_dir = out / seq
        seq_dir.mkdir(exist_ok=True)
        write_motion(seq_dir / "poses.motion", motions[seq])
        write_meshes(seq_dir / "gt.meshes", MeshSequence(motions[seq].frames, gt[seq].astype(np.float32)))

    t2 = time.perf_counter()
    static = {
        "faces": faces,
        "uvs": np.asarray(character.mesh.uvs, np.float64),
        "face_uvs": np.asarray(character.mesh.face_uvs, np.int64),
        "texture": _load_texture(character, config.seed),
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
    if config.jobs <= 1:
        _init_worker(static)
        for task in tasks:
            _render_chunk(*task)
        _WORKER.clear()
    else:

        for _ in process_map(_render_chunk, tasks, min(config.jobs, len(tasks)), _init_worker, (static,)):
            pass
    seconds["render"] = time.perf_counter() - t2  # ambient occlusion + ray casting + PNG writing

    if config.videos:
        t3 = time.perf_counter()
        names = [c.name for c in cameras]
        for seq in SEQUENCES:
            src = ImageFolderSource(out / seq)
            writers = VideoWriterSet(out / seq, names, config.width, config.height, config.fps)
            try:
                for f in frames[seq]:
                    for c in range(len(cameras)):
                        writers.write(c, *src.read(f, c))
            finally:
                writers.close()
        seconds["videos"] = time.perf_counter() - t3

    record = {"config": _jsonable(asdict(config)), "character": str(char_path.relative_to(out)) if
              char_path.is_relative_to(out) else str(char_path),
              "garment": {seq: {"max_offset_mm": float(np.linalg.norm(g.offsets, axis=-1).max()),
                                "spread_mm": [round(float(x), 3) for x in g.spread_mm],
                                "speed_mm_s": [round(float(x), 3) for x in g.speed_mm_s]}
                          for seq, g in garment.items()}}
    write_text_atomic(out / "synth.json", json.dumps(record, indent=2) + "\n")
    seconds["total"] = time.perf_counter() - t0
    log.info("synth %s: %s", out, {k: round(v, 2) for k, v in seconds.items()})
    return SynthResult(out, char_path, calib, cameras, train_cams, test_cams, frames, seconds)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    return x
