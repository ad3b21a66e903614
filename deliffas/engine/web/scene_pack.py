"""The scene of a web export: the mesh and its atlas, the normal-map gather, the outer offsets, the capture
cameras and the motion.

The motion is what the player poses per frame: for a template posed by skinning alone (a DDC character) the
per-frame bone transforms with the skin's indices and weights (the player blends them by LBS or DQS, as the
template does); for an SMPL template the shaped rest mesh, its joints, skin and pose blend shapes and per frame
the 72 pose values and the translation (the player runs ``deliffas.geometry.smpl.smpl_lbs``'s posing); for any
other template, or an SMPL motion whose betas change between frames, the posed vertices of every frame.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from deliffas.data.pose_motions import read_pose_motion
from deliffas.data.shard_meta import ShardMeta
from deliffas.engine.render import DEFAULT_FRAMES, motion_geometry_builder
from deliffas.engine.web.bundle import Bundle
from deliffas.geometry.smpl import blend_shapes
from deliffas.geometry.templates.ddc import DDCTemplate
from deliffas.geometry.templates.smpl import SMPLTemplate
from deliffas.io.body_models.smpl import NUM_JOINTS
from deliffas.io.motion import Motion

__all__ = ["pack_scene", "POSEDIRS_HALF_MAX_MM"]

log = logging.getLogger(__name__)

POSEDIRS_HALF_MAX_MM = 0.1
"""The pose blend shapes are stored as float16 when rounding them moves no vertex by more than this (mm) under
any pose (:func:`_rounding_bound`), else as float32."""


def _rounding_bound(error: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> float:
    """The most any vertex moves (mm, any pose) when the pose blend shapes' kept ``rows`` change by ``error``
    ((R, V * 3)): joint j's feature ``R_j - I`` has a Frobenius norm <= 2 sqrt(2), so its term moves a vertex by
    <= 2 sqrt(2) x the Frobenius norm of the vertex's (9, 3) error block, and skinning by ``weights`` ((V, J)) of
    rotations scales that by at most the sum of the vertex's |weights| (1 for SMPL's)."""
    if not len(rows):
        return 0.0
    full = np.zeros((9 * (NUM_JOINTS - 1), error.shape[1]))
    full[rows] = error
    per_joint = np.sqrt((full.reshape(NUM_JOINTS - 1, 9, -1, 3) ** 2).sum((1, 3)))  # (23, V)
    return float((2 * np.sqrt(2) * per_joint.sum(0) * np.abs(weights).sum(1)).max())


def _skin_top_k(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, K) joint indices (uint8) and weights of a dense (V, J) skin, K its most non-zero weights of a vertex;
    only exact zeros are dropped (a row with fewer is padded with joint 0 at weight 0)."""
    k = max(int((weights != 0).sum(1).max()), 1)
    order = np.argsort(weights == 0, axis=1, kind="stable")[:, :k]  # the non-zero ones first, in joint order
    w = np.take_along_axis(weights, order, 1)
    return np.where(w != 0, order, 0), w


def _pack_smpl(template: SMPLTemplate, params: torch.Tensor, bundle: Bundle) -> dict | None:
    """The SMPL motion entry (module docstring); None (posed vertices instead) when the betas change."""
    betas = params[:, 3 + 3 * NUM_JOINTS:]
    if not bool((betas == betas[:1]).all()):
        log.info("web export: the motion's betas change between frames; exporting its posed vertices per frame "
                 "(the player poses one shape)")
        return None
    v_shaped = template.v_template + blend_shapes(betas[:1], template.shapedirs)[0]  # (V, 3) mm
    joints = template.J_regressor @ v_shaped  # (24, 3), as smpl_lbs regresses them
    posedirs = template.posedirs.numpy()  # (207, V * 3) mm per unit of the pose feature
    rows = np.flatnonzero(np.any(posedirs != 0, axis=1))  # the pose feature's entries some vertex moves with
    kept = posedirs[rows]
    weights = template.lbs_weights.numpy()
    half = kept.astype("<f2")
    use_half = bool(np.isfinite(half).all()) and _rounding_bound(half - kept, rows, weights) <= POSEDIRS_HALF_MAX_MM
    stored = half if use_half else kept.astype("<f4")
    if use_half:  # the bundle holds no float16: its bytes, which the player decodes
        entry = bundle.add("posedirs", half.view(np.uint8).reshape(len(rows), -1), "uint8")
    else:
        entry = bundle.add("posedirs", stored)
    skin_idx, skin_w = _skin_top_k(weights)
    return {"kind": "smpl", "frames": len(params), "parents": [int(p) for p in template.parents],
            "v_shaped": bundle.add("v_shaped", v_shaped.numpy()), "joints": bundle.add("joints", joints.numpy()),
            "skin_indices": bundle.add("skin_indices", skin_idx, "uint8"),
            "skin_weights": bundle.add("skin_weights", skin_w),
            "pose_rows": [int(r) for r in rows], "posedirs": entry,
            "posedirs_dtype": "float16" if use_half else "float32",
            "posedirs_error_bound_mm": _rounding_bound(stored - kept, rows, weights),
            "poses": bundle.add("poses", params[:, 3:3 + 3 * NUM_JOINTS].numpy()),
            "transl": bundle.add("transl", (params[:, :3] * template.scale).numpy())}


def _pack_motion(template, dofs: np.ndarray, bundle: Bundle) -> dict:
    """Bone transforms and skin (a skinned template), an SMPL model's posing arrays, or posed vertices per frame."""
    params = torch.as_tensor(dofs, dtype=torch.float64)
    if type(template) is DDCTemplate:  # posed by skinning alone (a subclass poses by more)
        bones = template.bone_transforms(params)[:, :, :3, :].numpy()  # (N, Bn, 3, 4)
        return {"kind": "skinned", "skinning": template.skinning, "frames": len(dofs),
                "rest_verts": bundle.add("rest_verts", template.rest_verts.numpy()),
                "bones": bundle.add("bones", bones),
                "skin_indices": bundle.add("skin_indices", template.skin_indices.numpy(), "int32"),
                "skin_weights": bundle.add("skin_weights", template.skin_weights.numpy())}
    if type(template) is SMPLTemplate:  # exact, as above
        smpl = _pack_smpl(template, params.to(template.v_template), bundle)
        if smpl is not None:
            return smpl
    verts = template.pose(params).numpy()
    return {"kind": "vertices", "frames": len(dofs), "verts": bundle.add("verts", verts)}


def pack_scene(meta: ShardMeta, motion_path: Path, frames: int | None, bundle: Bundle) -> dict:
    """The scene's JSON entry, its arrays added to ``bundle``."""
    template, builder = motion_geometry_builder(meta)
    motion: Motion = read_pose_motion(motion_path, meta.template_spec(), template.num_dofs)
    n = min(frames or DEFAULT_FRAMES, motion.num_frames)
    gather = builder.gather
    cameras = [{"name": c.name, "K": np.asarray(c.K).tolist(), "world_to_cam": np.asarray(c.world_to_cam).tolist(),
                "width": int(c.width), "height": int(c.height)} for c in meta.cameras()]
    test = [int(c) for c in np.asarray(meta.test_cameras).reshape(-1)]
    with torch.no_grad():
        posing = _pack_motion(template, motion.dofs[:n], bundle)
    return {"motion_file": Path(motion_path).name, "num_verts": int(len(builder.offsets)),
            "faces": bundle.add("faces", builder.faces, "int32"),
            "uvs": bundle.add("uvs", meta.uvs), "face_uvs": bundle.add("face_uvs", meta.face_uvs, "int32"),
            "offsets": bundle.add("offsets", builder.offsets),
            "texel_verts": bundle.add("texel_verts", gather.vert_index.numpy(), "int32"),
            "texel_weights": bundle.add("texel_weights", gather.weights.numpy()),
            "cameras": cameras, "test_cameras": test, "motion": posing}
