"""The geometric stages of ``ingest``: the body model file, triangulation, usable frames and the body fit."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.body_models.smpl import load_smpl_model, write_smpl_model
from deliffas.io.cameras import Camera
from deliffas.geometry.body_fit import fit_body
from deliffas.geometry.body_fit_config import BodyFitConfig
from deliffas.geometry.body_fit_offsets import with_rest_offsets
from deliffas.geometry.body_landmarks import body_landmarks
from deliffas.geometry.smpl_body import make_procedural_smpl
from deliffas.geometry.templates import SMPL_MODEL_SUFFIXES, TemplateSpec, build_template, spec_from_file
from deliffas.geometry.triangulate import triangulate
from deliffas.data.ingest.config import IngestConfig
from deliffas.data.ingest.detect import BODY_LANDMARK_NAMES, KEYPOINTS
from deliffas.data.ingest.stages import Detections, load_npz, save_npz
from deliffas.data.subjects.capture_common import SMPL_NUM_BETAS

__all__ = ["prepare_body", "write_fitted_body", "triangulate_stage", "usable_frames", "fit_stage", "MIN_KEYPOINTS"]

log = logging.getLogger(__name__)

MIN_KEYPOINTS = 8
"""Triangulated keypoints (of the J) a frame needs to be fitted."""


def prepare_body(work: Path, body_model: str) -> TemplateSpec:
    """The SMPL template spec of the body model to fit, in ``work/body/``: the procedural body written there, or the
    user's file copied (with its ``<stem>_uv.obj`` when there is one)."""
    body = work / "body"
    body.mkdir(parents=True, exist_ok=True)
    if body_model == "procedural":
        model = body / "smpl_procedural.npz"
        if not model.is_file():
            model = make_procedural_smpl(body, seed=0)
    else:
        src = Path(body_model)
        if src.suffix not in SMPL_MODEL_SUFFIXES or not src.is_file():
            raise FileNotFoundError(f"--body-model {src}: expected an SMPL model file ({', '.join(SMPL_MODEL_SUFFIXES)}) "
                                    "or 'procedural'")
        model = body / src.name
        uv = src.with_name(f"{src.stem}_uv.obj")
        if uv.is_file() and not (body / uv.name).is_file():
            shutil.copyfile(uv, body / uv.name)
        if not model.is_file():
            shutil.copyfile(src, model)
    return spec_from_file(model, num_betas=SMPL_NUM_BETAS)


def write_fitted_body(out: Path, spec: TemplateSpec, rest_offsets_mm: np.ndarray) -> TemplateSpec:
    """``out/body/<stem>.npz``: the fitted body model, ``spec``'s model with the fit's per-vertex offsets in its
    rest shape (``BodyFitResult.rest_offsets_mm``), and its uv layout beside it; returns its spec."""
    src = spec.path("model")
    body = out / "body"
    body.mkdir(parents=True, exist_ok=True)
    model = body / f"{src.stem}.npz"
    write_smpl_model(model, with_rest_offsets(load_smpl_model(src), rest_offsets_mm,
                                                    float(spec.option("scale", 1000.0))))
    uv = src.with_name(f"{src.stem}_uv.obj")
    if uv.is_file():
        shutil.copyfile(uv, body / uv.name)
    return spec_from_file(model, num_betas=SMPL_NUM_BETAS)


def triangulate_stage(work: Path, dets: Detections, cameras: Sequence[Camera], config: IngestConfig) -> dict:
    """``keypoints3d.npz``: points (N, J, 3) mm, valid (N, J), used (N, J, C), reprojection_px (N, J, C)."""
    path = work / "keypoints3d.npz"
    done = load_npz(path)
    if done is not None:
        return done
    tri = triangulate(dets.keypoints, dets.conf, list(cameras), min_views=config.min_views)
    out = {"points": tri.points, "valid": tri.valid, "used": tri.used, "reprojection_px": tri.reprojection_px}
    save_npz(path, **out)
    return out


def usable_frames(tri: dict, alphas: np.ndarray, min_views: int) -> tuple[np.ndarray, dict[str, list[int]]]:
    """(N,) bool frames to fit, and the indices of the others by reason.

    A frame is usable when the person's mask is in at least ``min_views`` views and at least
    :data:`MIN_KEYPOINTS` keypoints were triangulated.
    """
    views = (alphas > 127).reshape(alphas.shape[0], alphas.shape[1], -1).any(axis=2).sum(axis=0)  # (N,)
    kps = tri["valid"].sum(axis=1)
    no_person = views == 0
    few_views = (views > 0) & (views < min_views)
    few_kps = ~no_person & ~few_views & (kps < MIN_KEYPOINTS)
    ok = ~(no_person | few_views | few_kps)
    reasons = {"no person in any view": np.flatnonzero(no_person).tolist(),
               f"a person in fewer than {min_views} views": np.flatnonzero(few_views).tolist(),
               f"fewer than {MIN_KEYPOINTS} keypoints triangulated": np.flatnonzero(few_kps).tolist()}
    return ok, reasons


def fit_stage(work: Path, spec: TemplateSpec, tri: dict, alphas: np.ndarray, cameras: Sequence[Camera],
              frames: list[int], config: IngestConfig) -> dict:
    """``fit.npz``: the fitted template rows of the usable frames, the rest offsets and the fit's residuals.

    Raises:
        ValueError: fewer than ``config.min_frames`` usable frames, listing the skipped ones by reason.
    """
    path = work / "fit.npz"
    done = load_npz(path)
    if done is not None:
        return done
    ok, reasons = usable_frames(tri, alphas, config.min_views)
    skipped = {r: [frames[i] for i in idx] for r, idx in reasons.items() if idx}
    if ok.sum() < config.min_frames:
        raise ValueError(f"{config.recording}: only {int(ok.sum())} of {len(frames)} frames show the person well "
                         f"enough to fit (at least {config.min_frames} needed, --min-frames); skipped: {skipped}")
    if skipped:
        log.warning("ingest: %d frames skipped: %s", len(frames) - int(ok.sum()), skipped)
    import torch

    template = build_template(spec, dtype=torch.float32)
    idx = np.flatnonzero(ok)
    conf = tri["valid"][idx].astype(np.float64)
    masks = np.ascontiguousarray(np.transpose(alphas[:, idx] > 127, (1, 0, 2, 3)))  # (N, C, H, W)
    landmarks = body_landmarks(template.v_template, template.J_regressor, template.lbs_weights, BODY_LANDMARK_NAMES)
    res = fit_body(template, np.nan_to_num(tri["points"][idx]), conf, landmarks, list(cameras), masks,
                   BodyFitConfig(iters_keypoints=config.fit_iters, iters_silhouette=max(1, config.fit_iters // 2),
                                 seed=config.seed), progress=config.progress,
                   frame_ids=np.asarray(frames, np.int64)[idx])
    out = {"frame_index": idx, "params": np.asarray(res.params, np.float64),
           "joint_error_mm": np.asarray(res.joint_error_mm, np.float64),
           "silhouette_iou": (np.asarray(res.silhouette_iou, np.float64) if res.silhouette_iou is not None
                              else np.full((len(idx), len(cameras)), np.nan)),
           "rest_offsets_mm": res.rest_offsets_mm, "joint_names": np.array([k.name for k in KEYPOINTS])}
    save_npz(path, **out)
    return out
