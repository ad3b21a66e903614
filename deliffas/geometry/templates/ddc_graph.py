"""The ``ddc_graph`` template kind: a DDC character posed through its embedded graph (formats doc 2.2)."""

from __future__ import annotations

import os
from typing import Literal

import torch

from deliffas.checks import check_finite, check_shape
from deliffas.io.formats.dynacap.character import Character, read_character
from deliffas.geometry.embedded_graph import EmbeddedDeformation, bind_embedded_graph, blend_bone_transforms
from deliffas.geometry.templates.base import TemplateKind, TemplateSpec, make_spec, register_template_kind
from deliffas.geometry.templates.ddc import DDCTemplate, Skinning, ddc_sources, read_ddc_motion, write_ddc_motion

__all__ = ["EmbeddedGraphTemplate", "Deformation", "ddc_graph_spec"]

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
        dof_match: as ``DDCTemplate``.
        dtype: as ``DDCTemplate``.
    """

    def __init__(self, character: Character, graph=None, skinning: Skinning = "dqs",
                 deformation: Deformation = "embedded_graph", dof_match: Literal["prefix", "exact"] = "prefix",
                 dtype: torch.dtype = torch.float32):
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
            skinning: overrides the template's mode.
            deformation: overrides the template's mode.

        Returns:
            (B, V, 3) vertices in template order, mm, world frame.
        """
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


def ddc_graph_spec(character_path: str | os.PathLike, skinning: Skinning = "dqs",
                   deformation: Deformation = "embedded_graph") -> TemplateSpec:
    """The ``ddc_graph`` spec of a ``.character`` file whose mesh has an embedded graph."""
    sources = ddc_sources(character_path)
    if "graph" not in sources:
        raise FileNotFoundError(f"{character_path}: no embedded graph (<mesh stem>_graph.obj next to the mesh)")
    return make_spec("ddc_graph", sources, skinning=skinning, deformation=deformation)


def _build(spec: TemplateSpec, dtype: torch.dtype) -> EmbeddedGraphTemplate:
    return EmbeddedGraphTemplate(read_character(spec.path("character")), skinning=spec.option("skinning", "dqs"),
                                 deformation=spec.option("deformation", "embedded_graph"), dtype=dtype)


register_template_kind(TemplateKind("ddc_graph", _build, ".motion", read_ddc_motion, write_ddc_motion))
