"""What the capture-dataset parsers (ZJU-MoCap, EasyMocap, THuman4.0, DNA-Rendering, ActorsHQ) share.

The SMPL template from a user's model file, SMPL pose rows from each dataset's parameter form,
lens distortion moved from the cameras into read-time undistortion of the frames, the test-camera
split, and the one-sequence ``Subject`` these datasets make.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.body_models.amass import read_smpl_motion
from deliffas.io.camera_conventions import DISTORTION, camera_distortion
from deliffas.io.formats.capture_frames import Undistortion
from deliffas.io.cameras import Camera
from deliffas.io.motion import Motion
from deliffas.io.body_models.smpl import SMPLModelData, load_smpl_model
from deliffas.geometry.smpl_params import smpl_to_motion, rest_root_joint, rhth_to_params
from deliffas.geometry.templates import SMPL_MODEL_SUFFIXES, TemplateSpec, spec_from_file, template_kind
from deliffas.data.subjects.base import SubjectOptions

__all__ = ["SMPL_NUM_BETAS", "SEQUENCE", "smpl_template", "smpl_model_data", "fit_betas", "rhth_motion",
           "split_distortion", "read_test_cameras", "user_motion", "require_template"]

log = logging.getLogger(__name__)

SMPL_NUM_BETAS = 10
"""Shape coefficients of the SMPL template made for a capture (extra betas of the files are dropped)."""

SEQUENCE = "training"
"""The sequence name of the one-sequence captures (the datasets here have no separate test motion)."""


def _model_path(options: SubjectOptions) -> Path | None:
    if options.template is not None and Path(options.template).suffix in SMPL_MODEL_SUFFIXES:
        return Path(options.template)
    extra = options.extra.get("smpl_model")
    return Path(str(extra)) if extra else None


def require_template(options: SubjectOptions, fmt: str) -> TemplateSpec:
    """The template the user names (``--template``: an SMPL model, or a ``.character`` / variant)."""
    model = _model_path(options)
    if model is not None:
        return spec_from_file(model, num_betas=SMPL_NUM_BETAS)
    if options.template is None:
        raise ValueError(f"{fmt}: needs the SMPL model file the capture was fitted with (SMPL is licensed; deliffas "
                         "cannot ship it): pass --template SMPL_MODEL.npz (or .pkl)")
    return spec_from_file(options.template, options.skinning, num_betas=SMPL_NUM_BETAS)


def smpl_template(options: SubjectOptions, fmt: str) -> TemplateSpec:
    """The ``smpl`` template spec of the user's model file; an error naming the option when there is none."""
    spec = require_template(options, fmt)
    if not template_kind(spec.kind).smpl_params:
        raise ValueError(f"{fmt}: its pose parameters are SMPL; --template must be an SMPL model file "
                         f"({', '.join(SMPL_MODEL_SUFFIXES)}), got {options.template}")
    return spec


def smpl_model_data(spec: TemplateSpec) -> SMPLModelData:
    return load_smpl_model(spec.path("model"))


def fit_betas(betas: np.ndarray, where: str) -> np.ndarray:
    """(SMPL_NUM_BETAS,) the first betas of a file's (B,) shape, zero-padded; dropping non-zero ones is logged."""
    betas = np.asarray(betas, np.float64).ravel()
    out = np.zeros(SMPL_NUM_BETAS)
    out[: min(len(betas), SMPL_NUM_BETAS)] = betas[:SMPL_NUM_BETAS]
    if np.any(betas[SMPL_NUM_BETAS:] != 0):
        log.warning("%s: %d shape coefficients, the SMPL template uses the first %d (the rest dropped)", where,
                    len(betas), SMPL_NUM_BETAS)
    return out


def rhth_motion(frames: Sequence[int], records: Sequence, model: SMPLModelData, where: str) -> Motion:
    """Template rows of EasyMocap ``Rh``/``Th`` records (``EasyMocapSmpl``), one per frame (exact, per-frame betas)."""
    rows = []
    for rec in records:  # frames
        betas = fit_betas(rec.shapes, where)
        rows.append(rhth_to_params(rec.Rh, rec.Th, rec.poses, betas, rest_root_joint(model, betas))[0])
    return Motion(np.asarray(frames, np.int64), np.stack(rows))


def user_motion(options: SubjectOptions, fallback: Path | None) -> Motion | None:
    """An AMASS-style ``--motions [training=]FILE.npz`` (frame k = row k), else ``fallback`` if it exists."""
    given = [s.partition("=")[2] if "=" in s else s for s in options.motions
             if "=" not in s or s.partition("=")[0] == SEQUENCE]
    path = Path(given[0]) if given else fallback
    if path is None or not path.is_file():
        return None
    return smpl_to_motion(read_smpl_motion(path), SMPL_NUM_BETAS)


def split_distortion(cameras: Sequence[Camera], fmt: str) -> tuple[tuple[Camera, ...], dict[int, Undistortion]]:
    """Cameras without lens distortion, and the undistortion each distorted camera's frames need.

    The frame sources undistort with the file's lens model (OpenCV pixel centres: K - 0.5 on cx, cy),
    so the pinhole cameras returned project the undistorted images exactly.
    """
    out, undistort = [], {}
    for i, cam in enumerate(cameras):
        d = camera_distortion(cam)
        if np.any(d != 0):
            K = np.array(cam.K, np.float64)
            K[0, 2] -= 0.5
            K[1, 2] -= 0.5
            undistort[i] = Undistortion(K, d)
        extra = {k: v for k, v in cam.extra.items() if k != DISTORTION}
        out.append(replace(cam, extra=extra))
    if undistort:
        log.warning("%s: %d of %d cameras carry lens distortion; their images and masks are undistorted when read "
                    "(cv2.initUndistortRectifyMap, same K)", fmt, len(undistort), len(cameras))
    return tuple(out), undistort


def read_test_cameras(root: Path, override: Sequence[int] | None) -> tuple[int, ...]:
    """Held-out cameras: ``override``, else ``root/split.json`` (``test_cameras``) or ``test_cameras.txt``, else none."""
    if override is not None:
        return tuple(sorted({int(c) for c in override}))
    sj = root / "split.json"
    if sj.is_file():
        return tuple(sorted(int(c) for c in json.loads(sj.read_text()).get("test_cameras", [])))
    tc = root / "test_cameras.txt"
    if tc.is_file():
        return tuple(sorted(int(tok) for tok in tc.read_text().split()))
    return ()
