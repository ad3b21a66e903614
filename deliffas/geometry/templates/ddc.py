"""The ``ddc`` template kind: a DDC character (skeleton + skin) posed by LBS or DQS.

``DDCTemplate.pose(dofs)`` = forward kinematics, per-bone transforms relative to the character's rest
pose (the ``.character``'s ``pose`` motion, frame 0 — the template OBJ is in that pose, formats doc
1.2), then per-vertex LBS or DQS with the C++ bone → joint rule (formats doc 1.5, 2.1b).
"""

from __future__ import annotations

import os
from typing import Literal

import numpy as np
import torch
from torch import nn
from jaxtyping import Float
from torch import Tensor

from deliffas.checks import check_finite, check_shape
from deliffas.io.formats.dynacap.character import Character, read_character, read_character_files, read_motion, write_motion
from deliffas.geometry.arrays import require_tensor
from deliffas.geometry.skeleton import SkeletonFK
from deliffas.geometry.skinning import dqs, lbs
from deliffas.geometry.templates.base import TemplateKind, TemplateSpec, make_spec, register_template_kind

__all__ = ["DDCTemplate", "Skinning", "ddc_sources", "ddc_spec", "read_ddc_motion", "write_ddc_motion"]

Skinning = Literal["dqs", "lbs"]


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

    def bone_transforms(self, dofs: Float[Tensor, "B D"]) -> Float[Tensor, "B Bn 4 4"]:
        """(B, D) -> (B, Bn, 4, 4) per-bone M_b = G_j(θ) · S_b · G_j(θ_rest)⁻¹."""
        glob = self.fk(dofs)[:, self.bone_joints]  # (B, Bn, 4, 4)
        return glob @ self.bone_scale @ self.rest_inverse

    def pose(self, dofs: Float[Tensor, "B D"], skinning: Skinning | None = None) -> Float[Tensor, "B V 3"]:
        """Posed template vertices.

        Args:
            dofs: (B, D) DOF values (DOF units) in the skeleton's DOF order.
            skinning: override the template's skinning mode.

        Returns:
            (B, V, 3) vertices in the template's vertex order, mm, world frame, in the template's
            dtype and on its device (torch-only: numpy motions go through ``deliffas.data.posing``).
        """
        require_tensor("dofs", dofs, "torch.as_tensor(dofs), or deliffas.data.posing.pose_frames for numpy")
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

    def forward(self, dofs: Float[Tensor, "B D"]) -> Float[Tensor, "B V 3"]:
        return self.pose(dofs)


def ddc_sources(character_path: str | os.PathLike) -> dict[str, str]:
    """Role -> path of every file a ``.character`` template is read from (the files it names and
    the mesh's ``segmentation.txt``, ``hand_segmentation.txt`` and ``<mesh>_graph.obj`` when present)."""
    files = read_character_files(character_path)
    mesh_dir = files.mesh.parent
    found = {"character": character_path, "skeleton": files.skeleton, "mesh": files.mesh, "skin": files.skin,
             "pose": files.pose, "segmentation": mesh_dir / "segmentation.txt",
             "hand_segmentation": mesh_dir / "hand_segmentation.txt",
             "graph": mesh_dir / f"{files.mesh.stem}_graph.obj"}
    return {role: str(p) for role, p in found.items() if p is not None and os.path.isfile(p)}


def ddc_spec(character_path: str | os.PathLike, skinning: Skinning = "dqs",
             outer_obj: str | os.PathLike | None = None) -> TemplateSpec:
    """The ``ddc`` spec of a ``.character`` file (``outer_obj``: a variant's per-vertex outer surface)."""
    if skinning not in ("dqs", "lbs"):
        raise ValueError(f"skinning must be 'dqs' or 'lbs', got {skinning!r}")
    return make_spec("ddc", {**ddc_sources(character_path), "outer": outer_obj}, skinning=skinning)


def _build(spec: TemplateSpec, dtype: torch.dtype) -> DDCTemplate:
    return DDCTemplate(read_character(spec.path("character")), spec.option("skinning", "dqs"), dtype=dtype)


def read_ddc_motion(path, spec: TemplateSpec, num_dofs: int | None = None):
    """A Skeletool ``.motion`` file as the template's DOF rows (the kinds ``ddc`` and ``ddc_graph``)."""
    return read_motion(path, num_dofs=num_dofs)


def write_ddc_motion(path, motion, fps: float) -> None:
    """DOF rows written as a Skeletool ``.motion`` (it records no frame rate)."""
    write_motion(path, motion)


register_template_kind(TemplateKind("ddc", _build, ".motion", read_ddc_motion, write_ddc_motion))
