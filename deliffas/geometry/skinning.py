"""Linear blend skinning and dual-quaternion skinning (formats doc 2.1), batched plain functions.

``lbs`` and ``dqs`` follow the geometry array policy (numpy in -> numpy out, torch in -> torch out
in the rest vertices' dtype and device; ``deliffas.geometry.arrays``); the quaternion helpers are
torch-only maths.
"""

from __future__ import annotations

import torch
from jaxtyping import Float, Integer
from torch import Tensor

from deliffas.checks import check_shape
from deliffas.geometry.arrays import ArrayLike, like, to_torch

__all__ = [
    "matrix_to_quaternion", "quaternion_to_matrix", "rigid_to_dual_quaternion",
    "lbs", "dqs",
]


def matrix_to_quaternion(R: Float[Tensor, "*B 3 3"]) -> Float[Tensor, "*B 4"]:
    """(..., 3, 3) rotations -> (..., 4) unit quaternions (w, x, y, z), numerically stable branch choice."""
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cand = torch.stack(
        [
            torch.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
        ],
        dim=-2,
    )  # (..., 4, 4): row i is 4·q·q_i, best conditioned where its diagonal term is largest
    diag = torch.stack([1 + tr, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                        1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1)
    best = diag.argmax(-1, keepdim=True)
    q = torch.gather(cand, -2, best.unsqueeze(-1).expand(*best.shape[:-1], 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0).to(q.dtype)


def quaternion_to_matrix(q: Float[Tensor, "*B 4"]) -> Float[Tensor, "*B 3 3"]:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)


def _qmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def rigid_to_dual_quaternion(T: Float[Tensor, "*B 4 4"]) -> tuple[Float[Tensor, "*B 4"], Float[Tensor, "*B 4"]]:
    """(..., 4, 4) rigid transforms -> real part (..., 4) and dual part (..., 4)."""
    real = matrix_to_quaternion(T[..., :3, :3])
    t = torch.cat([torch.zeros_like(T[..., :1, 3]), T[..., :3, 3]], -1)
    return real, 0.5 * _qmul(t, real)


def lbs(rest_verts: Float[ArrayLike, "V 3"], weights: Float[ArrayLike, "V Bn"],
        bone_transforms: Float[ArrayLike, "B Bn 4 4"]) -> Float[ArrayLike, "B V 3"]:
    """Linear blend skinning: v' = (Σ_b w_vb M_b) v.

    Args:
        rest_verts: (V, 3) rest-pose vertices, mm.
        weights: (V, Bn) dense skin weights (rows sum to 1).
        bone_transforms: (B, Bn, 4, 4) per-bone transforms relative to the rest pose.

    Returns:
        (B, V, 3) posed vertices, mm; numpy or torch as ``rest_verts``, in its dtype and on its device.
    """
    check_shape("rest_verts", rest_verts, "V 3")
    sizes = check_shape("weights", weights, "V Bn", {"V": rest_verts.shape[0]})
    check_shape("bone_transforms", bone_transforms, "B Bn 4 4", sizes)
    if not isinstance(rest_verts, torch.Tensor):
        return like(lbs(to_torch(rest_verts), to_torch(weights), to_torch(bone_transforms)), rest_verts)
    weights = to_torch(weights, rest_verts.dtype, rest_verts.device)
    bone_transforms = to_torch(bone_transforms, rest_verts.dtype, rest_verts.device)
    B, Bn = bone_transforms.shape[:2]
    blended = (weights @ bone_transforms[..., :3, :].reshape(B, Bn, 12)).reshape(B, -1, 3, 4)  # (B, V, 3, 4)
    return torch.einsum("bvij,vj->bvi", blended[..., :3], rest_verts) + blended[..., 3]


def dqs(
    rest_verts: Float[ArrayLike, "V 3"],
    indices: Integer[ArrayLike, "V K"],
    weights: Float[ArrayLike, "V K"],
    bone_transforms: Float[ArrayLike, "B Bn 4 4"],
    chunk: int = 64,
) -> Float[ArrayLike, "B V 3"]:
    """Dual-quaternion skinning as the C++ reference (formats doc 2.1).

    Each influence after the first has its dual quaternion negated when its real part's dot product
    with the *first* influence's is negative; the blend is divided by the norm of its real part.

    Args:
        rest_verts: (V, 3) mm.
        indices: (V, K) long bone index per influence, first = largest weight; -1 = padding.
        weights: (V, K) influence weights (0 for padding).
        bone_transforms: (B, Bn, 4, 4) rigid per-bone transforms relative to the rest pose.
        chunk: frames processed at once (bounds memory at chunk·V·K·8 values).

    Returns:
        (B, V, 3) posed vertices, mm; numpy or torch as ``rest_verts``, in its dtype and on its device.
    """
    check_shape("rest_verts", rest_verts, "V 3")
    check_shape("indices", indices, "V K", {"V": rest_verts.shape[0]})
    check_shape("weights", weights, "V K", {"V": rest_verts.shape[0], "K": indices.shape[1]})
    check_shape("bone_transforms", bone_transforms, "B Bn 4 4")
    if not isinstance(rest_verts, torch.Tensor):
        return like(dqs(to_torch(rest_verts), to_torch(indices), to_torch(weights), to_torch(bone_transforms), chunk),
                    rest_verts)
    indices = to_torch(indices, torch.long, rest_verts.device)
    weights = to_torch(weights, rest_verts.dtype, rest_verts.device)
    bone_transforms = to_torch(bone_transforms, rest_verts.dtype, rest_verts.device)
    real, dual = rigid_to_dual_quaternion(bone_transforms)  # (B, Bn, 4) each
    idx = indices.clamp(min=0)
    w = weights * (indices >= 0)
    out = []
    for start in range(0, bone_transforms.shape[0], chunk):
        r = real[start:start + chunk][:, idx]  # (b, V, K, 4)
        d = dual[start:start + chunk][:, idx]
        sign = torch.where((r * r[:, :, :1]).sum(-1) < 0, -1.0, 1.0).to(r.dtype)  # (b, V, K)
        ws = (w * sign).unsqueeze(-1)
        br = (ws * r).sum(2)  # (b, V, 4)
        bd = (ws * d).sum(2)
        norm = br.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        br, bd = br / norm, bd / norm
        R = quaternion_to_matrix(br)  # (b, V, 3, 3)
        conj = br * torch.tensor([1, -1, -1, -1], dtype=br.dtype, device=br.device)
        t = 2 * _qmul(bd, conj)[..., 1:]
        out.append(torch.einsum("bvij,vj->bvi", R, rest_verts) + t)
    return torch.cat(out, 0)
