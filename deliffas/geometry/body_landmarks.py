"""Points on the SMPL-layout body that a keypoint detector reports: joints, and surface points (ears, nose, toes,
heels) carried by one bone.

A keypoint detector's landmarks are of two kinds. Most stand for a joint centre (hips, knees, shoulders, ...):
the SMPL joint regressor row of that joint places them. Some lie on the skin: the ears, the nose, the tip of the
foot, the heel. Fitting those to a joint (the ears to SMPL's head joint, the toe tip to its foot joint) pulls the
body several cm off and makes its shape drift; :class:`BodyLandmarks` places them on the surface instead.

Each landmark is a fixed convex combination of rest vertices (``weights``, one row per landmark) moved rigidly
by one bone (``bones``): posed = ``A_bone @ rest``, with ``A`` the skinning transforms of
:func:`deliffas.geometry.smpl.batch_rigid_transform` and ``rest = weights @ (v_template + shapedirs betas)``, so a
landmark follows the shape. For a joint landmark this equals the posed joint exactly.

The surface landmarks are found on the mean-shape rest mesh by geometry, so they work for any mesh in SMPL's
layout and conventions (y up, facing +z, the body's left at +x; the procedural body or the user's SMPL file):

* ``l_ear`` / ``r_ear``: the head's vertices (skinned mostly to the head joint) furthest to the left / right;
* ``nose``: the head's vertices furthest forward;
* ``l_toe`` / ``r_toe``: the foot's vertices (skinned mostly to the ankle or foot joint, below the ankle joint)
  furthest forward;
* ``l_heel`` / ``r_heel``: those furthest back, in the lower half of the foot.

Each takes the mean of the vertices within :data:`EXTREME_BAND` of the body's height of the extreme.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float, Float64, Int64
from torch import Tensor

from deliffas.geometry.smpl import batch_rigid_transform, batch_rodrigues
from deliffas.geometry.smpl_body import SMPL_JOINT_NAMES

__all__ = ["BodyLandmarks", "SURFACE_LANDMARKS", "LANDMARK_NAMES", "EXTREME_BAND", "body_landmarks",
           "pose_landmarks", "posed_template_landmarks"]

EXTREME_BAND = 0.006
"""Vertices within this fraction of the body's height of a surface landmark's extreme are averaged (~1 cm)."""
_HEAD, _ANKLES, _FEET = 15, (7, 8), (10, 11)
SURFACE_LANDMARKS = {
    # name: (bones whose skinned vertices are searched, axis, sign (+1 max / -1 min), the bone that carries it)
    "l_ear": ((_HEAD,), 0, 1.0, _HEAD), "r_ear": ((_HEAD,), 0, -1.0, _HEAD), "nose": ((_HEAD,), 2, 1.0, _HEAD),
    "l_toe": ((_ANKLES[0], _FEET[0]), 2, 1.0, _FEET[0]), "r_toe": ((_ANKLES[1], _FEET[1]), 2, 1.0, _FEET[1]),
    "l_heel": ((_ANKLES[0], _FEET[0]), 2, -1.0, _ANKLES[0]), "r_heel": ((_ANKLES[1], _FEET[1]), 2, -1.0, _ANKLES[1]),
}
"""How each surface landmark is found (module docstring)."""
LANDMARK_NAMES = tuple(SMPL_JOINT_NAMES) + tuple(SURFACE_LANDMARKS)
"""Every landmark :func:`body_landmarks` knows: SMPL's 24 joints, then the surface points."""


@dataclass(frozen=True)
class BodyLandmarks:
    """J points on the body (module docstring).

    Attributes:
        names: (J,) landmark names (of :data:`LANDMARK_NAMES`).
        weights: (J, V) float64 convex combinations of rest vertices (a joint's regressor row, or a mean of
            surface vertices).
        bones: (J,) int64 the joint whose skinning transform carries each landmark.
        joints: (J,) int64 the SMPL joint a landmark stands for (its own index for a joint landmark), -1 for a
            surface landmark (the closed-form start of a body fit uses joints only).
    """

    names: tuple[str, ...]
    weights: Float64[np.ndarray, "J V"]
    bones: Int64[np.ndarray, "J"]
    joints: Int64[np.ndarray, "J"]

    def __len__(self) -> int:
        return len(self.names)


def _surface_row(rest: np.ndarray, lbs_weights: np.ndarray, name: str) -> np.ndarray:
    """(V,) weights of one surface landmark: the mean of the vertices at its extreme."""
    search, axis, sign, _ = SURFACE_LANDMARKS[name]
    owner = lbs_weights.argmax(1)
    region = np.isin(owner, search)
    if name.endswith(("toe", "heel")):
        ankle = _ANKLES[0] if name.startswith("l_") else _ANKLES[1]
        foot_top = rest[region, 1].max() if region.any() else 0.0
        region &= rest[:, 1] < min(_joint_height(rest, lbs_weights, ankle), foot_top)
        if name.endswith("heel") and region.any():  # the heel's back, not the calf above it
            low = rest[region, 1]
            region &= rest[:, 1] <= low.min() + 0.5 * (low.max() - low.min())
    if not region.any():
        raise ValueError(f"body landmark {name!r}: no vertex is skinned mostly to joints {search}")
    height = rest[:, 1].max() - rest[:, 1].min()
    coord = sign * rest[:, axis]
    pick = region & (coord >= coord[region].max() - EXTREME_BAND * height)
    row = np.zeros(len(rest))
    row[pick] = 1.0 / pick.sum()
    return row


def _joint_height(rest: np.ndarray, lbs_weights: np.ndarray, joint: int) -> float:
    """The rest height (y) of a joint, from its skinned vertices' weighted centre (no regressor needed)."""
    w = lbs_weights[:, joint]
    return float((w * rest[:, 1]).sum() / max(w.sum(), 1e-12))


def body_landmarks(v_template: np.ndarray | Tensor, J_regressor: np.ndarray | Tensor,
                   lbs_weights: np.ndarray | Tensor, names: tuple[str, ...] | list[str]) -> BodyLandmarks:
    """The landmarks ``names`` (of :data:`LANDMARK_NAMES`) of a body in SMPL layout.

    Args:
        v_template: (V, 3) mean-shape rest vertices (any unit).
        J_regressor: (24, V) joint regressor.
        lbs_weights: (V, 24) skinning weights.
        names: which landmarks, in order.

    Raises:
        ValueError: an unknown name (listing the known ones), or a body without vertices where one is searched.
    """
    rest, reg, skin = (np.asarray(torch.as_tensor(a).detach().cpu().double()) for a in (v_template, J_regressor,
                                                                                          lbs_weights))
    unknown = [n for n in names if n not in LANDMARK_NAMES]
    if unknown:
        raise ValueError(f"body landmarks {unknown}: unknown; expected names of {list(LANDMARK_NAMES)}")
    rows, bones, joints = [], [], []
    for name in names:
        if name in SURFACE_LANDMARKS:
            rows.append(_surface_row(rest, skin, name))
            bones.append(SURFACE_LANDMARKS[name][3])
            joints.append(-1)
        else:
            j = SMPL_JOINT_NAMES.index(name)
            rows.append(reg[j])
            bones.append(j)
            joints.append(j)
    return BodyLandmarks(tuple(names), np.stack(rows), np.asarray(bones, np.int64), np.asarray(joints, np.int64))


def pose_landmarks(landmarks: BodyLandmarks, rest: Float[Tensor, "J 3"] | Float[Tensor, "B J 3"],
                   transforms: Float[Tensor, "B 24 4 4"]) -> Float[Tensor, "B J 3"]:
    """(B, J, 3) posed landmarks: the rest points ``rest`` (``landmarks.weights @ v_shaped``) each moved by its
    bone's skinning transform (``batch_rigid_transform``'s second output), in their units, before any translation."""
    A = transforms[:, torch.as_tensor(landmarks.bones, device=transforms.device)]  # (B, J, 4, 4)
    return torch.einsum("bjik,bjk->bji", A[..., :3, :3], rest.expand(len(transforms), -1, -1)) + A[..., :3, 3]


def posed_template_landmarks(template, landmarks: BodyLandmarks, params: Float[Tensor, "B D"]
                             ) -> Float[Tensor, "B J 3"]:
    """(B, J, 3) landmarks of ``SMPLTemplate`` rows ``[transl, pose (72), betas]``, world units."""
    nj = len(SMPL_JOINT_NAMES)
    params = params.to(template.v_template)
    B = len(params)
    betas = params[:, 3 + 3 * nj:]
    v_shaped = template.v_template + torch.einsum("vkl,bl->bvk", template.shapedirs, betas)
    joints = torch.einsum("jv,bvk->bjk", template.J_regressor, v_shaped)
    rot = batch_rodrigues(params[:, 3:3 + 3 * nj].reshape(-1, 3)).reshape(B, nj, 3, 3)
    _, A = batch_rigid_transform(rot, joints, template.parents)
    w = torch.as_tensor(landmarks.weights, dtype=v_shaped.dtype, device=v_shaped.device)
    rest = torch.einsum("jv,bvk->bjk", w, v_shaped)
    return pose_landmarks(landmarks, rest, A) + params[:, None, :3] * template.scale
