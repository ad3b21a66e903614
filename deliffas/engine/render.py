"""Free-viewpoint rendering of a trained avatar driven by a motion (``deliffas render``)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import torch

from deliffas.checks import check_finite
from deliffas.io.cameras import Camera, look_at
from deliffas.data.pose_motions import motion_suffix, read_pose_motion
from deliffas.data.shard_meta import ShardMeta
from deliffas.geometry.atlas import TexelTable, UVAtlas
from deliffas.geometry.frame_geometry import FrameGeometryBuilder
from deliffas.geometry.templates import build_template
from deliffas.engine.avatar import load_avatar
from deliffas.engine.devices import resolve_device
from deliffas.engine.render_config import RenderConfig
from deliffas.engine.rays import device_camera_rays, paint_images, ray_query, stack_rays
from deliffas.engine.shading import PLAIN
from deliffas.fast.frame import describe_render_path, fast_render_camera, path_for_device, render_stream
from deliffas.engine.timing import StageTimer
from deliffas.fast.config import RenderPathConfig
from deliffas.geometry.raycast import UVRaycaster
from deliffas.io.infra.files import check_writable, claim_output_file
from deliffas.io.video import VIDEO_SUFFIXES, write_video

__all__ = ["RenderConfig", "render_video", "orbit_cameras", "render_images", "motion_geometry_builder", "find_motion",
           "DEFAULT_FRAMES"]

logger = logging.getLogger(__name__)


def orbit_cameras(reference: Camera, centers: np.ndarray, radius: float, height: float,
                  size: tuple[int, int] | None = None) -> list[Camera]:
    """One camera per frame on a circle around ``centers`` (N, 3), looking at it (y-up world, mm).

    The intrinsics are the reference camera's, rescaled to ``size``.
    """
    ref = reference.rescaled(*size) if size else reference
    cams = []
    n = len(centers)
    for i, c in enumerate(centers):
        a = 2 * math.pi * i / max(n, 1)
        eye = np.array([c[0] + radius * math.sin(a), height, c[2] + radius * math.cos(a)])
        cams.append(Camera(f"orbit{i:04d}", ref.K.copy(), look_at(eye, c), ref.width, ref.height))
    return cams


def render_images(model, normal_windows, geometry, faces, atlas, cameras: list[Camera], device: torch.device,
                  chunk_size: int = 262144, background: float = 0.0, render_path: RenderPathConfig = PLAIN):
    """Yield one (H, W, 3) uint8 image per frame: frame i seen by ``cameras[i]`` by ``render_path`` (the fast
    path: fast.frame on CPU, ``frames_in_flight()`` frames at once; the uvs from its ``uv`` on either path)."""
    path = describe_render_path(model, render_path, device)
    render_path = path_for_device(render_path, device)
    logger.log(logging.WARNING if path.fallback else logging.INFO, "render path: %s", path.line)

    @torch.no_grad()
    def frame(i: int) -> np.ndarray:
        cam = cameras[i]
        ni, no = (w.float()[None].to(device) for w in normal_windows(i))
        features = model.encode(ni, no)
        raycaster = UVRaycaster(geometry.inner[i], faces, geometry.outer[i], atlas)
        if render_path.fast:
            image = fast_render_camera(model, features, raycaster, cam, StageTimer(device), render_path, background)
        else:
            batch = stack_rays([device_camera_rays(raycaster, cam, device, render_path.uv)], [0]).to(device)
            rgb = model.shade_chunked(features, ray_query(batch, model.spec), chunk_size=chunk_size)
            image = paint_images(rgb, batch, 1, cam.height, cam.width, background)[0]
        check_finite(f"render: frame {i} ({cam.name}) colours", image)  # NaN would be written as black pixels
        return (image.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)

    yield from render_stream(frame, range(len(cameras)), render_path.frames_in_flight())


def motion_geometry_builder(meta) -> tuple:
    """The capture's template (float64) and the builder of its per-frame geometry (the shards' own
    atlas, texel table and outer offsets), so posed frames match the converted ones."""
    template = build_template(meta.template_spec(), dtype=torch.float64)
    table = TexelTable(meta.texel_face.astype(np.int64), meta.texel_bary, meta.texel_valid, meta.texel_valid)
    return template, FrameGeometryBuilder(meta.faces, meta.outer_offsets, table)


DEFAULT_FRAMES = 300
"""Frames of the motion rendered (or put into a web export) when the command does not say."""


def find_motion(meta: ShardMeta, motion: str | Path | None) -> Path:
    """``motion``, or the capture's first test (else training) motion file: the motion ``render`` plays.

    Raises:
        FileNotFoundError: no motion given and none found, saying to pass ``--motion``.
    """
    if motion:
        return Path(motion)
    suffix = motion_suffix(meta.template_spec().kind)
    if not meta.attrs.get("subject"):
        raise FileNotFoundError(f"the capture records no subject folder to take a *{suffix} motion from; pass --motion")
    subject = Path(meta.attrs["subject"])
    for seq in ("testing", "training"):
        for p in sorted((subject / seq).glob(f"*{suffix}")):
            return p
    raise FileNotFoundError(f"no *{suffix} motion under {subject}/testing or {subject}/training; pass --motion")


def render_video(cfg: RenderConfig) -> Path:
    """Render the run's avatar along a motion; returns the written path (written atomically)."""
    import cv2
    from tqdm import tqdm

    out = Path(cfg.out)
    if out.suffix and out.suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"video must end in .mp4 or .avi (or be a folder), got {out.name}")
    if cfg.camera is not None and cfg.orbit:
        raise ValueError("camera: a capture camera and an orbit exclude each other")
    if out.suffix:
        claim_output_file(out, cfg.overwrite)
    elif out.is_dir() and any(out.iterdir()):
        raise FileExistsError(f"{out}: not empty; give a new or empty folder for the PNG frames")
    else:
        check_writable(out, folder=True)
    device = resolve_device(cfg.device)
    model, record, meta = load_avatar(cfg.run, device)
    spec = meta.template_spec()
    template, builder = motion_geometry_builder(meta)
    motion_path = find_motion(meta, cfg.motion)
    motion = read_pose_motion(motion_path, spec, template.num_dofs)
    n = cfg.frames or min(motion.num_frames, DEFAULT_FRAMES)
    if n > motion.num_frames and not cfg.loop:
        raise ValueError(f"frames: {n} asked, the motion {motion_path} has {motion.num_frames}; pass --loop to "
                         "play it again from its start, or fewer --frames")
    if cfg.orbit and cfg.frames is None and n < 2 * cfg.fps:
        logger.warning("orbit: one turn over the motion's %d frames (%.2f s at %g fps); for a longer orbit pass "
                       "--frames %d --loop", n, n / cfg.fps, cfg.fps, int(4 * cfg.fps))
    rows = np.arange(n) % motion.num_frames
    inner = template.pose(torch.as_tensor(motion.dofs[rows], dtype=torch.float64)).numpy()
    check_finite(f"{motion_path}: the posed template", inner)
    geometry = builder.build(inner)
    T = model.config.temporal_window
    cams_all = meta.cameras()
    if cfg.orbit:
        centers = geometry.inner.mean(1)
        ref_centers = np.stack([c.center for c in cams_all])
        subject_c = centers.mean(0)
        radius = float(np.median(np.linalg.norm((ref_centers - subject_c)[:, [0, 2]], axis=1)))
        height = float(np.median(ref_centers[:, 1]))
        cameras = orbit_cameras(cams_all[0], centers, radius, height, cfg.size)
    else:
        index = cfg.camera if cfg.camera is not None else int(meta.test_cameras[0]) if len(meta.test_cameras) else 0
        if not 0 <= index < len(cams_all):
            raise ValueError(f"camera: {index} is not a capture camera (calibration indices 0..{len(cams_all) - 1})")
        base = cams_all[index]
        base = base.rescaled(*cfg.size) if cfg.size else base
        cameras = [base] * n
    atlas = UVAtlas(meta.uvs, meta.face_uvs)
    out.parent.mkdir(parents=True, exist_ok=True)
    images = render_images(model, lambda i: geometry.window(i, T), geometry, meta.faces, atlas, cameras, device,
                           cfg.chunk_size, render_path=cfg.render_path)
    bar = tqdm(images, total=n, desc="render", unit="frame", dynamic_ncols=True)
    if not out.suffix:
        out.mkdir(parents=True, exist_ok=True)
        for i, img in enumerate(bar):
            cv2.imwrite(str(out / f"{i:06d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        return out
    write_video(out, bar, cfg.fps)
    return out
