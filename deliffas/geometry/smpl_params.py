"""SMPL motions as the per-frame parameter rows of the ``smpl`` template, and back.

``SMPLTemplate`` (``deliffas.geometry.templates.smpl``) poses a frame from one row
``[transl (3, model units), axis-angle pose (72), betas (num_betas)]``; the rest of deliffas reads
per-frame pose parameters as a ``deliffas.io.dynacap.Motion`` (frame numbers + rows). These pure
functions convert an AMASS-style :class:`~deliffas.io.amass.SMPLMotion` to those rows and that
``Motion`` and back, without changing units or axes (AMASS's z-up world stays in the root
orientation and translation).
"""

from __future__ import annotations

import numpy as np

from deliffas.io.amass import SMPL_POSE_DIM, SMPLMotion
from deliffas.io.dynacap import Motion

__all__ = ["smpl_param_dim", "motion_to_params", "params_to_motion", "motion_to_dynacap"]


def smpl_param_dim(num_betas: int) -> int:
    """D = 3 + 72 + num_betas: the length of one ``smpl`` template parameter row."""
    return 3 + SMPL_POSE_DIM + int(num_betas)


def motion_to_params(motion: SMPLMotion, num_betas: int = 10) -> np.ndarray:
    """(N, 3 + 72 + num_betas) float64 rows ``[trans, smpl_pose, betas[:num_betas]]``.

    The pose is :attr:`SMPLMotion.smpl_pose` (SMPL-H/X: the shared 22 joints, hands zero); the same
    betas are repeated on every row.

    Raises:
        ValueError: ``num_betas`` outside 0..len(motion.betas).
    """
    if not 0 <= num_betas <= len(motion.betas):
        raise ValueError(f"num_betas: expected 0..{len(motion.betas)} (the motion's betas), got {num_betas}")
    n = motion.num_frames
    betas = np.broadcast_to(motion.betas[:num_betas], (n, num_betas))
    return np.concatenate([motion.trans, motion.smpl_pose, betas], axis=1)


def params_to_motion(params: np.ndarray, fps: float | None = None, gender: str | None = None,
                     min_betas: int = 10) -> SMPLMotion:
    """An SMPL motion (72-value poses) from template rows (N, 3 + 72 + NB).

    The betas are the first row's (they are shared by all frames of one subject; rows that differ
    raise). Fewer than ``min_betas`` betas are zero-padded, so the file keeps AMASS's >= 10.

    Raises:
        ValueError: a row length below 75, or betas that differ between rows.
    """
    params = np.asarray(params, np.float64)
    if params.ndim != 2 or params.shape[1] < 3 + SMPL_POSE_DIM:
        raise ValueError(f"params: expected shape (N, 3 + 72 + num_betas), got {params.shape}")
    betas = params[:, 3 + SMPL_POSE_DIM:]
    if len(betas) and not np.allclose(betas, betas[0], rtol=0, atol=1e-9):
        raise ValueError("params: the betas differ between rows; an SMPL motion has one shape")
    shared = betas[0] if len(betas) else np.zeros(betas.shape[1])
    shared = np.concatenate([shared, np.zeros(max(0, min_betas - len(shared)))])
    return SMPLMotion(params[:, 3:3 + SMPL_POSE_DIM].copy(), params[:, :3].copy(), shared, fps, gender)


def motion_to_dynacap(motion: SMPLMotion, num_betas: int = 10, first_frame: int = 0) -> Motion:
    """The motion as deliffas's per-frame pose parameters: the motion's ``frames`` when it has them,
    else ``first_frame .. first_frame + N - 1`` (int64), and ``dofs`` = :func:`motion_to_params` rows
    (N, 3 + 72 + num_betas)."""
    params = motion_to_params(motion, num_betas)
    frames = motion.frames if motion.frames is not None else np.arange(first_frame, first_frame + len(params))
    return Motion(np.asarray(frames, np.int64), params)
