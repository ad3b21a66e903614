"""Deformable templates: the ``DeformableTemplate`` protocol and the DDC (skeleton + skin) implementation.

``DDCTemplate.pose(dofs)`` = forward kinematics, per-bone transforms relative to the character's rest
pose (the ``.character``'s ``pose`` motion, frame 0 — the template OBJ is in that pose, formats doc
1.2), then per-vertex LBS or DQS with the C++ bone → joint rule (formats doc 1.5, 2.1b).
"""

from __future__ import annotations

from typing import Literal, Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn

from deliffas.checks import check_finite, check_shape
from deliffas.io.dynacap import Character
from deliffas.geometry.skeleton import SkeletonFK
from deliffas.geometry.skinning import dqs, lbs

__all__ = ["DeformableTemplate", "DDCTemplate", "Skinning", "EmbeddedGraphTemplate", "Deformation"]

Skinning = Literal["dqs", "lbs"]


@runtime_checkable
class DeformableTemplate(Protocol):
    """What the rest of deliffas needs from a template: posing plus fixed topology and UVs."""

    faces: torch.Tensor  # (F, 3) long
    uvs: torch.Tensor  # (T, 2)
    face_uvs: torch.Tensor  # (F, 3) long

    @property
    def num_verts(self) -> int: ...

    @property
    def num_dofs(self) -> int: ...

    def pose(self, dofs: torch.Tensor) -> torch.Tensor:
        """(B, D) pose parameters -> (B, V, 3) posed vertices, mm, world frame."""
        ...


def _bone_scales(character: Character, joint_ids: np.ndarray) -> np.ndarray:
    """Per-bone scale s: the scale of the joint's first child, or of its base joint without children."""
    skel = character.skeleton
    parents = skel.parent_indices()
    scales = np.array([j.scale for j in skel.joints])
    out = np.ones(len(joint_ids))
    for b, j in enumerate(joint_ids):
        children = np.nonzero(parents == j)[0]
        if len(children):
            out[b] = scales[children[0]]
        else:
            base = j
            while parents[base] >= 0 and not np.any(skel.joints[base].offset):
                base = parents[base]
            out[b] = scales[base]
    return out


class DDCTemplate(nn.Module):
    """A DDC character posed by skeletal skinning.

    Args:
        character: the parsed ``.character``.
        skinning: ``dqs`` (the original tools' default) or ``lbs``.
        dof_match: DOF joint-reference rule, see ``SkeletonFK``.
        dtype: float32 (default) or float64 for bit-level comparisons.
    """

    def __init__(self, character: Character, skinning: Skinning = "dqs",
                 dof_match: Literal["prefix", "exact"] = "prefix", dtype: torch.dtype = torch.float32):
        super().__init__()
        if skinning not in ("dqs", "lbs"):
            raise ValueError(f"skinning must be 'dqs' or 'lbs', got {skinning!r}")
        self.skinning = skinning
        self.fk = SkeletonFK(character.skeleton, dof_match, dtype)
        skel = character.skeleton
        joint_ids = np.array([skel.bone_joint_index(b) for b in character.skin.bones])
        scales = _bone_scales(character, joint_ids)
        mesh = character.mesh
        self.register_buffer("rest_verts", torch.tensor(mesh.verts, dtype=dtype))
        self.register_buffer("faces", torch.as_tensor(mesh.faces, dtype=torch.long))
        self.register_buffer("uvs", torch.tensor(mesh.uvs, dtype=dtype))
        face_uvs = mesh.face_uvs if mesh.face_uvs is not None else np.full_like(mesh.faces, -1)
        self.register_buffer("face_uvs", torch.tensor(np.asarray(face_uvs), dtype=torch.long))
        self.register_buffer("bone_joints", torch.as_tensor(joint_ids, dtype=torch.long))
        S = torch.eye(4, dtype=dtype).repeat(len(joint_ids), 1, 1)
        S[:, :3, :3] *= torch.tensor(scales, dtype=dtype)[:, None, None]
        self.register_buffer("bone_scale", S)
        self.register_buffer("skin_indices", torch.as_tensor(character.skin.indices, dtype=torch.long))
        self.register_buffer("skin_weights", torch.tensor(character.skin.weights, dtype=dtype))
        self.register_buffer("skin_dense", torch.tensor(character.skin.dense(), dtype=dtype))
        self.register_buffer("rest_dofs", torch.tensor(character.rest_dofs, dtype=dtype))
        rest_glob = self.fk(self.rest_dofs[None])[0, self.bone_joints]  # (Bn, 4, 4)
        self.register_buffer("rest_inverse", torch.linalg.inv(rest_glob))

    @property
    def num_verts(self) -> int:
        return int(self.rest_verts.shape[0])

    @property
    def num_dofs(self) -> int:
        return self.fk.num_dofs

    def bone_transforms(self, dofs: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B, Bn, 4, 4) per-bone M_b = G_j(θ) · S_b · G_j(θ_rest)⁻¹."""
        glob = self.fk(dofs)[:, self.bone_joints]  # (B, Bn, 4, 4)
        return glob @ self.bone_scale @ self.rest_inverse

    def pose(self, dofs: torch.Tensor, skinning: Skinning | None = None) -> torch.Tensor:
        """Posed template vertices.

        Args:
            dofs: (B, D) DOF values (DOF units) in the skeleton's DOF order.
            skinning: override the template's skinning mode.

        Returns:
            (B, V, 3) vertices in the template's vertex order, mm, world frame.
        """
        check_shape("dofs", dofs, "B D", {"D": self.num_dofs})
        check_finite("dofs", dofs)
        dofs = dofs.to(device=self.rest_verts.device, dtype=self.rest_verts.dtype)
        M = self.bone_transforms(dofs)
        mode = skinning or self.skinning
        if mode == "lbs":
            return lbs(self.rest_verts, self.skin_dense, M)
        if mode == "dqs":
            return dqs(self.rest_verts, self.skin_indices, self.skin_weights, M)
        raise ValueError(f"skinning must be 'dqs' or 'lbs', got {mode!r}")

    def forward(self, dofs: torch.Tensor) -> torch.Tensor:
        return self.pose(dofs)


Deformation = Literal["embedded_graph", "per_vertex"]


class EmbeddedGraphTemplate(DDCTemplate):
    """A DDC character posed through its embedded graph (formats doc 2.2), with the DDC parameters.

    ``deformation="embedded_graph"`` interpolates skinned node transforms with the graph weights
    (DDC's posing: with zero parameters, node-resampled skinning); ``"per_vertex"`` applies each
    vertex's own blended bone transform to the canonical vertices (with zero parameters exactly
    ``DDCTemplate.pose``). Both share the canonical deformation by node angles, node translations
    and per-vertex deltas.

    Args:
        character: the parsed ``.character``; its ``graph`` is bound when ``graph`` is None.
        graph: a binding from ``deliffas.geometry.embedded_graph.bind_embedded_graph``.
        skinning: ``dqs`` (C++ default: dual-quaternion blend of node transforms) or ``lbs``.
        deformation: ``embedded_graph`` or ``per_vertex``.
        dof_match, dtype: as ``DDCTemplate``.
    """

    def __init__(self, character: Character, graph=None, skinning: Skinning = "dqs",
                 deformation: Deformation = "embedded_graph", dof_match: Literal["prefix", "exact"] = "prefix",
                 dtype: torch.dtype = torch.float32):
        from deliffas.geometry.embedded_graph import EmbeddedDeformation, bind_embedded_graph

        super().__init__(character, skinning, dof_match, dtype)
        if deformation not in ("embedded_graph", "per_vertex"):
            raise ValueError(f"deformation must be 'embedded_graph' or 'per_vertex', got {deformation!r}")
        if graph is None:
            if character.graph is None:
                raise ValueError(f"{character.path}: the character has no embedded graph "
                                 f"(<mesh stem>_graph.obj next to the mesh); pass graph=")
            graph = bind_embedded_graph(character.mesh.verts, character.mesh.faces, character.graph,
                                        character.segmentation)
        self.deformation = deformation
        self.graph = graph
        self.deformer = EmbeddedDeformation(graph, character.mesh.verts, dtype)
        self.register_buffer("node_skin_indices", self.skin_indices[self.deformer.node_verts].clone())
        self.register_buffer("node_skin_weights", self.skin_weights[self.deformer.node_verts].clone())

    @property
    def num_nodes(self) -> int:
        return self.deformer.num_nodes

    def node_transforms(self, dofs: torch.Tensor,
                        skinning: Skinning | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Skinned node transforms (B, K, 3, 3) and (B, K, 3) mm for DOFs (B, D)."""
        from deliffas.geometry.embedded_graph import blend_bone_transforms

        check_shape("dofs", dofs, "B D", {"D": self.num_dofs})
        M = self.bone_transforms(dofs.to(self.rest_verts))
        return blend_bone_transforms(self.node_skin_indices, self.node_skin_weights, M, skinning or self.skinning)

    def pose(self, dofs: torch.Tensor, node_angles: torch.Tensor | None = None,
             node_translations: torch.Tensor | None = None, vertex_deltas: torch.Tensor | None = None,
             skinning: Skinning | None = None, deformation: Deformation | None = None) -> torch.Tensor:
        """Posed vertices.

        Args:
            dofs: (B, D) DOF values.
            node_angles: (B, K, 3) Euler angles (α, β, γ) of R = R_z R_y R_x per node, rad.
            node_translations: (B, K, 3) Δt per node, mm.
            vertex_deltas: (B, V, 3) per-vertex delta d_i, mm (rest frame).
            skinning, deformation: override the template's modes.

        Returns:
            (B, V, 3) vertices in template order, mm, world frame.
        """
        from deliffas.geometry.embedded_graph import blend_bone_transforms

        check_shape("dofs", dofs, "B D", {"D": self.num_dofs})
        check_finite("dofs", dofs)
        dofs = dofs.to(device=self.rest_verts.device, dtype=self.rest_verts.dtype)
        mode = deformation or self.deformation
        blend = skinning or self.skinning
        canonical = self.deformer.canonical(node_angles, node_translations, vertex_deltas)  # (B|1, V, 3)
        M = self.bone_transforms(dofs)
        if mode == "embedded_graph":
            R, t = blend_bone_transforms(self.node_skin_indices, self.node_skin_weights, M, blend)
            return self.deformer.pose(canonical, R, t)
        if mode == "per_vertex":
            if blend == "lbs":
                A = torch.einsum("vb,nbij->nvij", self.skin_dense, M[:, :, :3, :])  # (B, V, 3, 4)
                R, t = A[..., :3], A[..., 3]
            else:
                R, t = blend_bone_transforms(self.skin_indices, self.skin_weights, M, blend)
            return torch.einsum("bvij,bvj->bvi", R, canonical.expand(R.shape[0], -1, -1)) + t
        raise ValueError(f"deformation must be 'embedded_graph' or 'per_vertex', got {mode!r}")
