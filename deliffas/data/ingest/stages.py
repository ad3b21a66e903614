"""The stages of ``ingest`` between reading the streams and writing the subject, each resumable.

Every stage leaves its result in ``OUT/.ingest/`` (written atomically) and a later run with ``--resume`` loads
it instead of running the stage again: detection per camera (``detect_<cam>.npz`` + the prepared frames
``frames/<cam>/<frame>.png``), triangulation (``keypoints3d.npz``), the body fit (``fit.npz``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.infra.files import atomic_path, write_bytes_atomic
from deliffas.io.recording import Stream, StreamReader
from deliffas.data.ingest.detect import PersonDetector
from deliffas.data.ingest.frames import FramePlan
from deliffas.data.ingest.masks import person_mask

__all__ = ["WORK_DIR", "Detections", "detect_camera", "load_detections", "frame_path", "save_npz", "load_npz",
           "refine_masks"]

log = logging.getLogger(__name__)

WORK_DIR = ".ingest"
"""The folder of ``OUT`` holding the stages' results (removed when the ingest finishes)."""
PNG_FAST = 1
"""PNG compression level of the prepared frames (work files: speed over size)."""


def save_npz(path: Path, **arrays) -> None:
    """``np.savez_compressed`` written atomically (a temporary name, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def load_npz(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a stage's result, or None when the stage has not finished."""
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def frame_path(work: Path, camera: str, frame: int) -> Path:
    """The prepared (undistorted, resized) RGB frame of one camera."""
    return work / "frames" / camera / f"{frame:06d}.png"


class Detections:
    """Per camera, per frame: keypoints (C, N, J, 2) pixels, confidences (C, N, J), mask probabilities
    (C, N, H, W) uint8 (x 255), and each camera's detection time in seconds."""

    def __init__(self, keypoints: np.ndarray, conf: np.ndarray, masks: np.ndarray, seconds: np.ndarray):
        self.keypoints, self.conf, self.masks, self.seconds = keypoints, conf, masks, seconds


def detect_camera(stream: Stream, plan: FramePlan, frames: range, work: Path, progress: bool) -> Path:
    """Decode, prepare and detect one camera's frames; write the frames and ``detect_<cam>.npz``.

    Returns:
        The path of the camera's ``detect_<cam>.npz`` (an existing one is kept: the camera is done).
    """
    import cv2
    from tqdm import tqdm

    out = work / f"detect_{stream.camera}.npz"
    if out.is_file():
        return out
    kps, conf, masks = [], [], []
    t0 = time.perf_counter()
    with StreamReader(stream) as reader, PersonDetector(video=True) as detector:
        for f, rgb in tqdm(reader.frames(frames), total=len(frames), desc=f"detect {stream.camera}",
                           disable=not progress, unit="frame"):
            img = plan(rgb)
            p = frame_path(work, stream.camera, f)
            p.parent.mkdir(parents=True, exist_ok=True)
            ok, buf = cv2.imencode(".png", img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, PNG_FAST])
            if not ok:
                raise RuntimeError(f"{p}: PNG encoding failed")
            write_bytes_atomic(p, buf.tobytes())
            det = detector(img)
            kps.append(det.keypoints)
            conf.append(det.conf)
            masks.append(np.round(det.mask * 255.0).astype(np.uint8))
    save_npz(out, keypoints=np.stack(kps), conf=np.stack(conf), masks=np.stack(masks),
             seconds=np.float64(time.perf_counter() - t0))
    return out


def load_detections(work: Path, cameras: Sequence[str]) -> Detections:
    """Every camera's ``detect_<cam>.npz`` stacked in camera order."""
    parts = [load_npz(work / f"detect_{c}.npz") for c in cameras]
    missing = [c for c, p in zip(cameras, parts) if p is None]
    if missing:
        raise FileNotFoundError(f"{work}: no detections of cameras {missing}")
    return Detections(np.stack([p["keypoints"] for p in parts]), np.stack([p["conf"] for p in parts]),
                      np.stack([p["masks"] for p in parts]), np.array([float(p["seconds"]) for p in parts]))


def refine_masks(masks: np.ndarray, points: np.ndarray, valid: np.ndarray,
                 cameras: Sequence[Camera]) -> np.ndarray:
    """(C, N, H, W) uint8 alpha: each detector mask kept where the triangulated person projects.

    Args:
        masks: (C, N, H, W) uint8 person probability x 255.
        points: (N, J, 3) float64 mm, triangulated keypoints; valid: (N, J) bool.
        cameras: C cameras at the masks' size.
    """
    out = np.zeros_like(masks)
    for c, cam in enumerate(cameras):
        for n in range(masks.shape[1]):
            pts = points[n][valid[n]]
            anchors = None
            if len(pts):
                pix, z = cam.project(pts)
                anchors = pix[z > 0]
            if len(pts) and (anchors is None or not len(anchors)):
                continue  # the person is behind this camera: nothing of the mask is them
            out[c, n] = person_mask(masks[c, n].astype(np.float32) / 255.0, anchors)
    return out
