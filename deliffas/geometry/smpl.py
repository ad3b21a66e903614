"""SMPL's linear blend skinning as plain batched functions (smplx ``lbs.py`` style).

``batch_rodrigues``, ``blend_shapes``, ``batch_rigid_transform`` and ``smpl_lbs`` take every model
array as an argument and create new tensors on the inputs' device and dtype. The template that holds
the arrays is :class:`deliffas.geometry.templates.smpl.SMPLTemplate`; the model file is read by
:func:`deliffas.io.body_models.smpl.load_smpl_model`.
"""

from __future__ import annotations

import torch
from jaxtyping import Float, Integer
from torch import Tensor

__all__ = ["batch_rodrigues", "blend_shapes", "batch_rigid_transform", "smpl_lbs"]


def batch_rodrigues(rot_vecs: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3 3"]:
    """(N, 3) axis-angle vectors -> (N, 3, 3) rotation matrices (zero vector -> identity)."""
    angle = torch.linalg.norm(rot_vecs + 1e-8, dim=1, keepdim=True)  # (N, 1), as smplx
    axis = rot_vecs / angle
    cos, sin = torch.cos(angle)[:, :, None], torch.sin(angle)[:, :, None]
    x, y, z = axis.unbind(1)
    zeros = torch.zeros_like(x)
    K = torch.stack([zeros, -z, y, z, zeros, -x, -y, x, zeros], dim=1).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=rot_vecs.dtype, device=rot_vecs.device)[None]
    return eye + sin * K + (1 - cos) * torch.bmm(K, K)


def blend_shapes(betas: Float[Tensor, "B NB"], shapedirs: Float[Tensor, "V 3 NB"]) -> Float[Tensor, "B V 3"]:
    """(B, NB) betas, (V, 3, NB) shapedirs -> (B, V, 3) displacements."""
    return torch.einsum("bl,mkl->bmk", betas, shapedirs)


def batch_rigid_transform(rot_mats: Float[Tensor, "B J 3 3"], joints: Float[Tensor, "B J 3"],
                          parents: Integer[Tensor, "J"]) -> tuple[Float[Tensor, "B J 3"], Float[Tensor, "B J 4 4"]]:
    """Global joint transforms of a kinematic tree (parents precede children).

    Args:
        rot_mats: (B, J, 3, 3) local rotations.
        joints: (B, J, 3) rest joint locations.
        parents: (J,) long, -1 for the root.

    Returns:
        posed joints (B, J, 3) and skinning transforms (B, J, 4, 4) relative to the rest pose.
    """
    B, J = joints.shape[:2]
    rel = joints.clone()
    rel[:, 1:] -= joints[:, parents[1:]]
    local = torch.zeros(B, J, 4, 4, dtype=joints.dtype, device=joints.device)
    local[..., :3, :3] = rot_mats
    local[..., :3, 3] = rel
    local[..., 3, 3] = 1
    chain = [local[:, 0]]
    for j in range(1, J):  # a loop over the 24 joints
        chain.append(chain[int(parents[j])] @ local[:, j])
    glob = torch.stack(chain, dim=1)  # (B, J, 4, 4)
    posed_joints = glob[..., :3, 3]
    rel_T = glob.clone()
    rel_T[..., :3, 3] -= torch.einsum("bjik,bjk->bji", glob[..., :3, :3], joints)
    return posed_joints, rel_T


def smpl_lbs(betas: Float[Tensor, "B NB"], pose: Float[Tensor, "B P"], v_template: Float[Tensor, "V 3"],
             shapedirs: Float[Tensor, "V 3 NB"], posedirs: Float[Tensor, "207 V3"], J_regressor: Float[Tensor, "J V"],
             parents: Integer[Tensor, "J"], lbs_weights: Float[Tensor, "V J"]
             ) -> tuple[Float[Tensor, "B V 3"], Float[Tensor, "B J 3"]]:
    """SMPL: shape blend shapes, joint regression, pose blend shapes, linear blend skinning.

    Args:
        betas: (B, NB). pose: (B, 72) axis-angle (global orientation first).
        v_template: (V, 3). shapedirs: (V, 3, NB). posedirs: (207, V * 3).
        J_regressor: (24, V). parents: (24,) long. lbs_weights: (V, 24).

    Returns:
        vertices (B, V, 3) and joints (B, 24, 3), model units.
    """
    B = betas.shape[0]
    v_shaped = v_template + blend_shapes(betas, shapedirs)  # (B, V, 3)
    joints = torch.einsum("jv,bvk->bjk", J_regressor, v_shaped)  # (B, 24, 3)
    rot = batch_rodrigues(pose.reshape(-1, 3)).reshape(B, -1, 3, 3)  # (B, 24, 3, 3)
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
    pose_feature = (rot[:, 1:] - eye).reshape(B, -1)  # (B, 207)
    v_posed = v_shaped + (pose_feature @ posedirs).reshape(B, -1, 3)
    posed_joints, T = batch_rigid_transform(rot, joints, parents)
    M = torch.einsum("vj,bjik->bvik", lbs_weights, T)  # (B, V, 4, 4)
    verts = torch.einsum("bvik,bvk->bvi", M[..., :3, :3], v_posed) + M[..., :3, 3]
    return verts, posed_joints
