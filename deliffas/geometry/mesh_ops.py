"""Per-face and per-vertex normals of triangle meshes, batched, in torch or numpy.

Vertex normals follow the original DELIFFAS renderer (dynacap-formats.md 3.3): the normalised
sum of the *unnormalised* face normals cross(v1 - v0, v2 - v0) of the faces around a vertex
(area-weighted; outward for counter-clockwise faces).

Both functions follow the geometry array policy (``deliffas.geometry.arrays``): numpy arrays or
torch tensors in, the same kind out; torch inputs keep their device and dtype; numpy inputs are
computed in torch and converted back (float64 stays float64).
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float, Integer

from deliffas.checks import check_shape
from deliffas.geometry.arrays import ArrayLike, is_numpy, to_numpy, to_torch

__all__ = ["face_normals", "vertex_normals", "ZERO_NORMAL_EPS"]

ZERO_NORMAL_EPS = 1e-12
"""A summed vertex normal whose length is <= this (mm^2) is treated as zero: the unit normal is
(0, 0, 0) and ``valid`` is False. This happens for isolated vertices (no faces) and for vertices
whose faces are all degenerate or cancel exactly."""


def _face_normals_t(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    v0 = verts[..., faces[:, 0], :]  # (..., F, 3)
    v1 = verts[..., faces[:, 1], :]
    v2 = verts[..., faces[:, 2], :]
    return torch.cross(v1 - v0, v2 - v0, dim=-1)


def face_normals(verts: Float[ArrayLike, "*B V 3"], faces: Integer[ArrayLike, "F 3"]) -> Float[ArrayLike, "*B F 3"]:
    """Unnormalised face normals cross(v1 - v0, v2 - v0) (length = 2 x face area).

    Args:
        verts: (..., V, 3) float, mm.
        faces: (F, 3) int, 0-based indices into ``verts``.

    Returns:
        (..., F, 3), same kind (numpy / torch), dtype and device as ``verts``.
    """
    check_shape("verts", verts, "* V 3")
    check_shape("faces", faces, "F 3")
    v = to_torch(verts)
    out = _face_normals_t(v, to_torch(faces, torch.long, v.device))
    return to_numpy(out) if is_numpy(verts) else out


def vertex_normals(verts: Float[ArrayLike, "*B V 3"], faces: Integer[ArrayLike, "F 3"], *, return_valid: bool = False
                   ) -> Float[ArrayLike, "*B V 3"] | tuple[Float[ArrayLike, "*B V 3"], Bool[ArrayLike, "*B V"]]:
    """Unit vertex normals: normalised sum of the unnormalised normals of the incident faces.

    Args:
        verts: (..., V, 3) float, mm, world frame (any number of leading batch dimensions).
        faces: (F, 3) int, 0-based indices into ``verts``.
        return_valid: also return the (..., V) bool mask of vertices with a non-zero normal.

    Returns:
        normals (..., V, 3), same kind, dtype and device as ``verts``. Vertices whose summed
        normal has length <= ``ZERO_NORMAL_EPS`` (isolated or only degenerate faces) get
        (0, 0, 0); with ``return_valid`` the pair (normals, valid) is returned.
    """
    check_shape("verts", verts, "* V 3")
    check_shape("faces", faces, "F 3")
    v = to_torch(verts)
    f = to_torch(faces, torch.long, v.device)
    lead = v.shape[:-2]
    num_verts = v.shape[-2]
    vb = v.reshape(-1, num_verts, 3)  # (B, V, 3)
    fn = _face_normals_t(vb, f)  # (B, F, 3)
    acc = torch.zeros_like(vb)
    for k in range(3):  # three corners, not a loop over faces
        acc.index_add_(1, f[:, k], fn)
    length = acc.norm(dim=-1, keepdim=True)  # (B, V, 1)
    valid = length[..., 0] > ZERO_NORMAL_EPS
    normals = torch.where(valid[..., None], acc / length.clamp_min(ZERO_NORMAL_EPS), torch.zeros_like(acc))
    normals = normals.reshape(*lead, num_verts, 3)
    valid = valid.reshape(*lead, num_verts)
    if is_numpy(verts):
        normals, valid = to_numpy(normals), to_numpy(valid)
    return (normals, valid) if return_valid else normals
