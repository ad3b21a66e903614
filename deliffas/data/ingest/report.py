"""The last stage of ``ingest``: the subject's files, the overlay pictures and ``ingest_report.json``."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.infra.text_lines import write_text_atomic
from deliffas.io.recording import Stream
from deliffas.geometry.templates import TemplateSpec, build_template
from deliffas.geometry.triangulate import Triangulation, reprojection_summary
from deliffas.data.ingest.config import INGEST_MARKER, IngestConfig
from deliffas.data.ingest.detect import DETECTOR_VERSION, KEYPOINT_NAMES
from deliffas.data.ingest.frames import FramePlan
from deliffas.data.ingest.stages import Detections, frame_path, save_npz
from deliffas.data.ingest.write import (FPS_DEFAULT, draw_overlay, silhouette, split_frames, write_cameras_and_split,
                                        write_sequence)

__all__ = ["write_outputs", "KEYPOINTS_FILE"]

log = logging.getLogger(__name__)

OVERLAY_HEIGHT = 640
"""Height of each camera's tile in the overlay pictures."""


def _median(x) -> float | None:
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return round(float(np.median(x)), 4) if len(x) else None


def _read_rgb(work: Path, camera: str, frame: int) -> np.ndarray:
    import cv2

    p = frame_path(work, camera, frame)
    bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"{p}: prepared frame missing; run the ingest again with --overwrite")
    return bgr[..., ::-1]


def _posed(spec: TemplateSpec, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import torch

    template = build_template(spec, dtype=torch.float32)
    with torch.no_grad():
        verts = template.pose(torch.as_tensor(params, dtype=torch.float32)).numpy()
    return verts.astype(np.float64), template.faces.numpy()


def _overlays(out: Path, work: Path, names: Sequence[str], plans: Sequence[FramePlan], frames: list[int],
              fit: dict, alphas: np.ndarray, tri: dict, spec: TemplateSpec, count: int) -> list[str]:
    """``overlays/frame_<f>.png``: every camera side by side, for ``count`` evenly spaced fitted frames."""
    import cv2

    idx = fit["frame_index"]
    picks = np.unique(np.linspace(0, len(idx) - 1, min(count, len(idx))).round().astype(int))
    verts, faces = _posed(spec, fit["params"][picks])
    written = []
    for k, p in enumerate(picks):
        n = int(idx[p])
        tiles = []
        for c, (name, plan) in enumerate(zip(names, plans)):
            pts = tri["points"][n][tri["valid"][n]]
            kp = plan.camera.project(pts)[0] if len(pts) else None
            tile = draw_overlay(_read_rgb(work, name, frames[n]), alphas[c, n], silhouette(verts[k], faces, plan.camera),
                                kp, f"{name} f{frames[n]}")
            s = OVERLAY_HEIGHT / tile.shape[0]
            tiles.append(cv2.resize(tile, (max(1, round(tile.shape[1] * s)), OVERLAY_HEIGHT), interpolation=cv2.INTER_AREA))
        path = out / "overlays" / f"frame_{frames[n]:06d}.png"
        path.parent.mkdir(exist_ok=True)
        cv2.imwrite(str(path), np.concatenate(tiles, axis=1)[..., ::-1])
        written.append(str(path.relative_to(out)))
    return written


def _camera_rows(names, streams: Sequence[Stream], plans, dets: Detections, alphas, tri: dict, fit: dict) -> list[dict]:
    rows = []
    used = tri["used"]
    rep = np.where(used, tri["reprojection_px"], np.nan)
    for c, name in enumerate(names):
        rows.append({"camera": name, "stream": str(streams[c].path), "stream_size": [streams[c].width, streams[c].height],
                     "note": plans[c].note, "detector_person_fraction": round(float((dets.conf[c].max(axis=1) > 0).mean()), 4),
                     "mask_person_fraction": round(float((alphas[c] > 127).reshape(alphas.shape[1], -1).any(axis=1).mean()), 4),
                     "median_reprojection_px": _median(rep[:, :, c]),
                     "outlier_fraction": round(float(((tri["reprojection_px"][:, :, c] >= 0) & ~used[:, :, c]).sum()
                                                     / max(1, np.isfinite(tri["reprojection_px"][:, :, c]).sum())), 4),
                     "median_silhouette_iou": _median(fit["silhouette_iou"][:, c]),
                     "detect_images_per_second": round(len(dets.conf[c]) / max(1e-9, float(dets.seconds[c])), 2)})
    return rows


KEYPOINTS_FILE = "keypoints.npz"
"""The subject's keypoints: ``frames`` (N,) stream frame numbers, ``keypoint_names`` (J,), ``camera_names`` (C,),
``keypoints2d`` (C, N, J, 2) pixels of the written images and ``conf2d`` (C, N, J), ``points3d`` (N, J, 3) world mm
(NaN where not triangulated), ``valid3d`` (N, J), ``used`` (N, J, C) the inlier views, ``reprojection_px``
(N, J, C; NaN where a view has no detection, as ``deliffas.geometry.triangulate.Triangulation``)."""


def write_outputs(out: Path, work: Path, config: IngestConfig, spec: TemplateSpec, plans: Sequence[FramePlan],
                  streams: Sequence[Stream], frames: list[int], dets: Detections, tri: dict, alphas: np.ndarray,
                  fit: dict, seconds: dict[str, float], calib: Path) -> dict:
    """Write the subject (:mod:`.write`), the overlays and, last, ``ingest_report.json``; return the report."""
    t = time.perf_counter()
    names = [s.camera for s in streams]
    idx = [int(i) for i in fit["frame_index"]]
    fitted = [frames[i] for i in idx]
    row_of = {f: k for k, f in enumerate(fitted)}
    seqs = split_frames(fitted, config.test_frames)
    size = plans[0].size
    fps = streams[0].fps or FPS_DEFAULT
    for name, seq_frames in seqs.items():
        rows = fit["params"][[row_of[f] for f in seq_frames]]
        write_sequence(out / name, seq_frames, len(names), lambda f, c: _read_rgb(work, names[c], f),
                       lambda f, c: alphas[c, idx[row_of[f]]], rows, spec, fps, size)
    test = list(range(len(names) - config.test_cameras, len(names)))
    write_cameras_and_split(out, [p.camera for p in plans], test, seqs)
    save_npz(out / KEYPOINTS_FILE, frames=np.asarray(frames, np.int64), keypoint_names=np.asarray(KEYPOINT_NAMES),
             camera_names=np.asarray(names), keypoints2d=dets.keypoints, conf2d=dets.conf, points3d=tri["points"],
             valid3d=tri["valid"], used=tri["used"], reprojection_px=tri["reprojection_px"])
    seconds["write subject"] = time.perf_counter() - t
    t = time.perf_counter()
    overlays = _overlays(out, work, names, plans, frames, fit, alphas, tri, spec, config.overlays)
    seconds["overlays"] = time.perf_counter() - t
    triang = Triangulation(tri["points"], tri["valid"], tri["used"], tri["reprojection_px"])
    skipped = sorted(set(frames) - set(fitted))
    report = {
        "recording": str(Path(config.recording).resolve()), "calibration": str(Path(calib).resolve()),
        "detector": f"MediaPipe Pose {DETECTOR_VERSION} (full model, segmentation)",
        "image_size": list(size), "frames": {"read": len(frames), "fitted": len(fitted), "skipped": skipped,
                                             "sequences": {k: [v[0], v[-1]] for k, v in seqs.items()}},
        "test_cameras": [names[c] for c in test],
        "cameras": _camera_rows(names, streams, plans, dets, alphas, tri, fit),
        "keypoints": reprojection_summary(triang, list(KEYPOINT_NAMES), names),
        "fit": {"median_joint_error_mm": _median(fit["joint_error_mm"]),
                "joint_error_mm_by_keypoint": {k: _median(fit["joint_error_mm"][:, j]) for j, k in enumerate(KEYPOINT_NAMES)},
                "median_silhouette_iou": _median(fit["silhouette_iou"])},
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
        "overlays": overlays,
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(config).items()},
    }
    write_text_atomic(out / INGEST_MARKER, json.dumps(report, indent=2) + "\n")
    return report
