"""Batched, device-agnostic forward kinematics of Skeletool DOF skeletons (formats doc 1.3)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import nn

from deliffas.checks import check_shape
from deliffas.io.formats.dynacap.skeleton import Skeleton

__all__ = ["axis_angle_to_matrix", "forward_kinematics", "SkeletonFK", "kinematic_levels"]


def axis_angle_to_matrix(axes: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Rotation matrices about unit ``axes`` by ``angles`` (Rodrigues).

    Args:
        axes: (..., 3) unit vectors.
        angles: (...) radians.

    Returns:
        (..., 3, 3) right-handed rotations.
    """
    x, y, z = axes.unbind(-1)
    c, s = torch.cos(angles), torch.sin(angles)
    C = 1 - c
    return torch.stack(
        [
            c + x * x * C, x * y * C - z * s, x * z * C + y * s,
            y * x * C + z * s, c + y * y * C, y * z * C - x * s,
            z * x * C - y * s, z * y * C + x * s, c + z * z * C,
        ],
        dim=-1,
    ).reshape(*angles.shape, 3, 3)


def kinematic_levels(parents: np.ndarray) -> list[np.ndarray]:
    """Group joints by depth in the tree so each level can be composed in one batched step."""
    depth = np.full(len(parents), -1)
    for j in range(len(parents)):
        chain, cur = [], j
        while cur >= 0 and depth[cur] < 0:
            chain.append(cur)
            cur = parents[cur]
        base = depth[cur] if cur >= 0 else -1
        for k in reversed(chain):
            base += 1
            depth[k] = base
    return [np.nonzero(depth == d)[0] for d in range(depth.max() + 1)]


def forward_kinematics(
    params: torch.Tensor,
    parents: torch.Tensor,
    offsets: torch.Tensor,
    axes: torch.Tensor,
    revolute: torch.Tensor,
    levels: list[torch.Tensor],
) -> torch.Tensor:
    """Global joint transforms from joint parameters.

    T_j = T_parent(j) · Translate(offset_j) · Motion_j(p_j), Motion = rotation by p_j about the axis
    (revolute) or translation p_j · axis (prismatic, mm).

    Args:
        params: (B, J) joint parameters (radians or mm).
        parents: (J,) long, -1 for the root.
        offsets: (J, 3) scale-multiplied offsets, mm.
        axes: (J, 3) rotation axes / translation directions.
        revolute: (J,) bool.
        levels: joint indices per tree depth (root level first).

    Returns:
        (B, J, 4, 4) world transforms (rotation, translation in mm).
    """
    B, J = params.shape
    rot = axis_angle_to_matrix(axes.expand(B, J, 3), params * revolute)  # (B, J, 3, 3)
    trans = offsets + (params * (~revolute)).unsqueeze(-1) * axes  # (B, J, 3)
    local = torch.zeros(B, J, 4, 4, dtype=params.dtype, device=params.device)
    local[..., :3, :3] = rot
    local[..., :3, 3] = trans
    local[..., 3, 3] = 1
    glob = local.clone()
    for level in levels[1:]:
        glob[:, level] = glob[:, parents[level]] @ local[:, level]
    return glob


@dataclass(frozen=True)
class _Tree:
    parents: np.ndarray
    offsets: np.ndarray
    axes: np.ndarray
    revolute: np.ndarray
    dof_weights: np.ndarray


class SkeletonFK(nn.Module):
    """Forward kinematics of one skeleton as a module (its arrays are buffers, so ``.to()`` moves them).

    Args:
        skeleton: the parsed ``.skeleton``.
        dof_match: how DOF joint references resolve: ``prefix`` reproduces the original C++ tools
            (default), ``exact`` the PyTorch port; they differ only for finger flex1 DOFs of DDC.
    """

    def __init__(self, skeleton: Skeleton, dof_match: Literal["prefix", "exact"] = "prefix",
                 dtype: torch.dtype = torch.float32):
        super().__init__()
        parents = skeleton.parent_indices()
        self.num_joints = skeleton.num_joints
        self.num_dofs = skeleton.num_dofs
        self.register_buffer("parents", torch.as_tensor(parents))
        self.register_buffer("offsets", torch.tensor(np.stack([j.offset * j.scale for j in skeleton.joints]), dtype=dtype))
        # Revolute axes are normalised on load by the C++ reader; prismatic directions are used as written.
        axes = np.stack([j.axis / np.linalg.norm(j.axis) if j.type == "revolute" else j.axis for j in skeleton.joints])
        self.register_buffer("axes", torch.tensor(axes, dtype=dtype))
        self.register_buffer("revolute", torch.tensor([j.type == "revolute" for j in skeleton.joints]))
        self.register_buffer("dof_weights", torch.tensor(skeleton.dof_weights(dof_match), dtype=dtype))
        self._levels = [torch.as_tensor(lv) for lv in kinematic_levels(parents)]

    def _apply(self, fn, recurse=True):  # keep level index tensors on the buffers' device
        super()._apply(fn, recurse)
        self._levels = [lv.to(self.parents.device) for lv in self._levels]
        return self

    def joint_params(self, dofs: torch.Tensor) -> torch.Tensor:
        """(B, D) DOF values -> (B, J) joint parameters (Σ_d weight_dj · x_d)."""
        check_shape("dofs", dofs, "B D", {"D": self.num_dofs})
        return dofs.to(self.dof_weights.dtype) @ self.dof_weights

    def forward(self, dofs: torch.Tensor) -> torch.Tensor:
        """(B, D) DOF values -> (B, J, 4, 4) global joint transforms (mm)."""
        return forward_kinematics(self.joint_params(dofs), self.parents, self.offsets, self.axes,
                                  self.revolute, self._levels)
