"""SMPL motions as the per-frame parameter rows of the ``smpl`` template, and back.

``SMPLTemplate`` (``deliffas.geometry.templates.smpl``) poses a frame from one row
``[transl (3, model units), axis-angle pose (72), betas (num_betas)]``; the rest of deliffas reads
per-frame pose parameters as a ``deliffas.io.motion.Motion`` (frame numbers + rows). These pure
functions convert an AMASS-style :class:`~deliffas.io.body_models.amass.SMPLMotion` to those rows and that
``Motion`` and back, without changing units or axes (AMASS's z-up world stays in the root
orientation and translation). Capture datasets store the same pose in other forms; the
conversions are exact and live here too: EasyMocap / ZJU-MoCap ``Rh``/``Th`` (:func:`rhth_to_params`,
:func:`params_to_rhth`) and SMPL-X's body pose (:func:`smplx_to_smpl_pose`).
"""

from __future__ import annotations

import numpy as np

from deliffas.io.body_models.amass import SMPL_BODY_POSE_DIM, SMPL_POSE_DIM, SMPLMotion
from deliffas.io.camera_conventions import matrix_to_rotvec, rotvec_to_matrix
from deliffas.io.motion import Motion
from deliffas.io.body_models.smpl import SMPLModelData

__all__ = ["smpl_param_dim", "motion_to_params", "params_to_motion", "smpl_to_motion", "rest_root_joint",
           "rhth_to_params", "params_to_rhth", "smplx_to_smpl_pose"]


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


def smpl_to_motion(motion: SMPLMotion, num_betas: int = 10, first_frame: int = 0) -> Motion:
    """The motion as deliffas's per-frame pose parameters: the motion's ``frames`` when it has them,
    else ``first_frame .. first_frame + N - 1`` (int64), and ``dofs`` = :func:`motion_to_params` rows
    (N, 3 + 72 + num_betas)."""
    params = motion_to_params(motion, num_betas)
    frames = motion.frames if motion.frames is not None else np.arange(first_frame, first_frame + len(params))
    return Motion(np.asarray(frames, np.int64), params)


def rest_root_joint(model: SMPLModelData, betas: np.ndarray) -> np.ndarray:
    """(3,) float64 the shaped rest pelvis joint ``J_regressor[0] @ (v_template + shapedirs betas)``, model units."""
    betas = np.asarray(betas, np.float64).ravel()
    nb = min(len(betas), model.num_betas)
    shaped = model.v_template + model.shapedirs[:, :, :nb] @ betas[:nb]  # (V, 3)
    return model.J_regressor[0] @ shaped


def rhth_to_params(Rh: np.ndarray, Th: np.ndarray, poses: np.ndarray, betas: np.ndarray,
                   root_joint: np.ndarray) -> np.ndarray:
    """SMPL template rows ``[transl, pose (72), betas]`` of EasyMocap's ``Rh``/``Th`` form.

    EasyMocap poses the body with its root at the rest pelvis J0, then rotates the result about the
    **origin** and translates: ``v = R(Rh) X + Th``. SMPL's root rotation turns about J0 itself:
    ``v = G (X - J0) + J0 + transl``. With G = R(Rh) R(poses[:3]) both agree when
    ``transl = Th + R(Rh) J0 - J0``.

    Args:
        Rh: (N, 3) axis-angle.
        Th: (N, 3) translation, model units (metres).
        poses: (N, >= 66) (SMPL 72; SMPL-H/X: the first 66 are the shared 22 joints, the rest are
            dropped and SMPL's hands set to zero).
        betas: (NB,) shape, shared.
        root_joint: (3,) ``rest_root_joint(model, betas)``.

    Returns:
        (N, 3 + 72 + NB) float64.
    """
    Rh, Th = np.atleast_2d(Rh).astype(np.float64), np.atleast_2d(Th).astype(np.float64)
    poses = np.atleast_2d(poses).astype(np.float64)
    n = len(Rh)
    pose = np.zeros((n, SMPL_POSE_DIM))
    k = SMPL_POSE_DIM if poses.shape[1] == SMPL_POSE_DIM else SMPL_BODY_POSE_DIM
    pose[:, :k] = poses[:, :k]
    transl = np.empty((n, 3))
    for i in range(n):  # frames
        R = rotvec_to_matrix(Rh[i])
        pose[i, :3] = matrix_to_rotvec(R @ rotvec_to_matrix(pose[i, :3]))
        transl[i] = Th[i] + R @ root_joint - root_joint
    betas = np.broadcast_to(np.asarray(betas, np.float64).ravel(), (n, np.size(betas)))
    return np.concatenate([transl, pose, betas], axis=1)


def params_to_rhth(params: np.ndarray, root_joint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of :func:`rhth_to_params`: (Rh (N, 3), Th (N, 3), poses (N, 72) with poses[:, :3] = 0)."""
    params = np.atleast_2d(np.asarray(params, np.float64))
    Rh = params[:, 3:6].copy()
    Th = np.stack([t - rotvec_to_matrix(r) @ root_joint + root_joint for t, r in zip(params[:, :3], Rh)])
    poses = params[:, 3:3 + SMPL_POSE_DIM].copy()
    poses[:, :3] = 0.0
    return Rh, Th, poses


def smplx_to_smpl_pose(global_orient: np.ndarray, body_pose: np.ndarray) -> np.ndarray:
    """(N, 72) SMPL pose from SMPL-X's global orientation (N, 3) and 21-joint body pose (N, 63).

    The 22 shared joints are copied; SMPL's two hand joints (22, 23) are zero. SMPL-X's jaw, eyes,
    fingers and expression have no SMPL joint and are dropped.
    """
    go = np.atleast_2d(np.asarray(global_orient, np.float64))
    body = np.asarray(body_pose, np.float64).reshape(len(go), -1)
    out = np.zeros((len(go), SMPL_POSE_DIM))
    out[:, :3] = go
    out[:, 3:SMPL_BODY_POSE_DIM] = body[:, :SMPL_BODY_POSE_DIM - 3]
    return out
