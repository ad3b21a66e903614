"""The ingested recording written as a DynaCap subject, and the overlay pictures of what was found.

Layout (docs/data.md): ``cameras.calibration`` (pinhole, undistorted, at the written size), ``body/`` (the SMPL
model file), ``training/`` and ``testing/`` each with ``rgb_<W>_<H>/`` RGBA images (alpha = the person mask)
and ``poses.npz`` (the fitted SMPL rows), ``split.json`` + ``test_cameras.txt``; ``check``, ``convert``,
``train`` read it unchanged. ``cameras.calibration`` is written after the images, so a folder left by a crash
is not taken for a capture.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.formats.dynacap.calibration import write_calibration
from deliffas.io.formats.dynacap.frames import write_image
from deliffas.io.infra.text_lines import write_text_atomic
from deliffas.io.motion import Motion
from deliffas.geometry.templates import TemplateSpec, template_kind

__all__ = ["FPS_DEFAULT", "split_frames", "write_sequence", "write_cameras_and_split", "silhouette", "draw_overlay"]

FPS_DEFAULT = 25.0
"""Frame rate recorded in the motions when the streams state none (image folders)."""


def split_frames(frames: Sequence[int], test_fraction: float) -> dict[str, list[int]]:
    """The frames of the ``training`` and (the last ``test_fraction``) ``testing`` sequences."""
    frames = [int(f) for f in frames]
    n_test = int(round(len(frames) * test_fraction)) if len(frames) > 1 else 0
    n_test = min(n_test, len(frames) - 1)
    out = {"training": frames[: len(frames) - n_test]}
    if n_test:
        out["testing"] = frames[len(frames) - n_test:]
    return out


def write_sequence(seq_dir: Path, frames: Sequence[int], num_cameras: int, images, alphas, params: np.ndarray,
                   spec: TemplateSpec, fps: float, size: tuple[int, int]) -> None:
    """One sequence: its RGBA images and its motion.

    Args:
        frames: capture frame numbers; images(frame, camera) -> (H, W, 3) uint8; alphas(frame, camera) -> (H, W)
            uint8; params: (len(frames), D) float64 template rows.
    """
    root = seq_dir / f"rgb_{size[0]}_{size[1]}"
    for f in frames:
        for c in range(num_cameras):
            write_image(root, f, c, images(f, c), alphas(f, c))
    kind = template_kind(spec.kind)
    kind.write_motion(seq_dir / f"poses{kind.motion_suffix}", Motion(np.asarray(frames, np.int64), params), fps)


def write_cameras_and_split(out: Path, cameras: Sequence[Camera], test_cameras: Sequence[int],
                            sequences: dict[str, list[int]]) -> None:
    """``split.json``, ``test_cameras.txt`` and, last, ``cameras.calibration``."""
    test = sorted(int(c) for c in test_cameras)
    split = {"camera_names": [c.name for c in cameras],
             "train_cameras": [c for c in range(len(cameras)) if c not in test], "test_cameras": test,
             "sequences": {s: {"frames": [f[0], f[-1] + 1]} for s, f in sequences.items()}}
    write_text_atomic(out / "split.json", json.dumps(split, indent=2) + "\n")
    write_text_atomic(out / "test_cameras.txt", "".join(f"{c}\n" for c in test))
    write_calibration(out / "cameras.calibration", list(cameras))


def silhouette(verts: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) bool: the mesh (V, 3) mm filled face by face in ``camera`` (faces behind it are left out)."""
    import cv2

    pix, z = camera.project(np.asarray(verts, np.float64))
    out = np.zeros((camera.height, camera.width), np.uint8)
    front = (z[faces] > 1.0).all(axis=1)
    tri = np.round(pix[faces[front]] * 4).astype(np.int32)  # 2 fractional bits
    cv2.fillPoly(out, list(tri), 1, lineType=cv2.LINE_8, shift=2)
    return out.astype(bool)


def draw_overlay(rgb: np.ndarray, alpha: np.ndarray, body: np.ndarray | None, keypoints: np.ndarray | None,
                 label: str) -> np.ndarray:
    """(H, W, 3) uint8: the image, the mask tinted green, the fitted body's outline red, keypoints yellow."""
    import cv2

    img = rgb.astype(np.float32)
    a = (alpha.astype(np.float32) / 255.0)[..., None]
    img = img * (1 - 0.45 * a) + np.array([0, 255, 0], np.float32) * 0.45 * a
    img = np.ascontiguousarray(np.clip(img, 0, 255).astype(np.uint8))
    if body is not None:
        contours, _ = cv2.findContours(body.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, contours, -1, (255, 40, 40), max(1, img.shape[0] // 400))
    if keypoints is not None:
        for x, y in keypoints[np.isfinite(keypoints).all(axis=1)]:
            cv2.circle(img, (int(x), int(y)), max(2, img.shape[0] // 200), (255, 230, 0), -1)
    cv2.putText(img, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
    return img
