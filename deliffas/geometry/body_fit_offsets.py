"""Per-vertex offsets of the fitted body (SMPL+D): one displacement along each rest vertex normal, shared by all frames.

The silhouette stage of :func:`deliffas.geometry.body_fit.fit_body` fits them with the pose (``BodyFitConfig.offsets``)
so the body follows what the shape space cannot: clothing, hair, a body outside the model's shape directions. They
are part of the rest shape: ``v_template + shapedirs . betas + offsets * normals`` is posed by SMPL's joints,
pose blend shapes and skinning as the plain body is, so a model file whose ``v_template`` holds them
(:func:`with_rest_offsets`) reproduces the fitted body exactly. Two priors keep them plausible: squared
differences of neighbouring offsets (``offset_smooth``) and their squared size (``offset_prior``), both in cm^2.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from jaxtyping import Float, Float64
from torch import Tensor

from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.shell import mesh_edges
from deliffas.geometry.smpl import smpl_lbs
from deliffas.geometry.templates.smpl import SMPLTemplate
from deliffas.io.body_models.smpl import SMPLModelData

__all__ = ["RestOffsets", "with_rest_offsets", "OFFSETS_LR"]

OFFSETS_LR = 100.0
"""Adam's learning rate of the offsets (mm), in units of ``BodyFitConfig.lr``."""


class RestOffsets:
    """The offsets (V,) mm along the template's rest normals (mean shape), a tensor Adam moves, and their priors."""

    def __init__(self, template: SMPLTemplate):
        ref = template.v_template
        self.template = template
        self.normals = vertex_normals(ref.detach(), template.faces).to(ref)  # (V, 3)
        self.edges = torch.as_tensor(mesh_edges(template.faces.cpu().numpy())[0], device=ref.device)  # (E, 2)
        self.mm = torch.zeros(template.num_verts, dtype=ref.dtype, device=ref.device, requires_grad=True)

    def vectors(self) -> Float[Tensor, "V 3"]:
        """(V, 3) mm: each offset along its rest normal."""
        return self.mm[:, None] * self.normals

    def joint_shift(self) -> Float[Tensor, "24 3"]:
        """(24, 3) mm: how the offsets move the regressed rest joints."""
        return self.template.J_regressor @ self.vectors()

    def pose(self, params: Float[Tensor, "B D"]) -> Float[Tensor, "B V 3"]:
        """``SMPLTemplate.pose`` of rows [transl, pose (72), betas] with the offsets in the rest shape."""
        t = self.template
        transl = params[:, :3] * t.scale
        verts, _ = smpl_lbs(params[:, 75:], params[:, 3:75], t.v_template + self.vectors(), t.shapedirs, t.posedirs,
                            t.J_regressor, t.parents, t.lbs_weights)
        return verts + transl[:, None]

    def priors(self) -> dict[str, Tensor]:
        """``offset_smooth``: mean squared difference over mesh edges, ``offset_prior``: mean square; cm^2."""
        d = self.mm / 10.0
        diff = d[self.edges[:, 0]] - d[self.edges[:, 1]]
        return {"offset_smooth": (diff ** 2).mean(), "offset_prior": (d ** 2).mean()}

    def as_numpy(self) -> Float64[np.ndarray, "V 3"]:
        """(V, 3) float64 mm: :meth:`vectors`, detached."""
        return self.vectors().detach().double().cpu().numpy()


def with_rest_offsets(model: SMPLModelData, rest_offsets_mm: Float64[np.ndarray, "V 3"], scale: float = 1000.0
                      ) -> SMPLModelData:
    """``model`` with ``rest_offsets_mm`` (``BodyFitResult.rest_offsets_mm``) added to its ``v_template`` (model
    units: ``scale`` mm each)."""
    offsets = np.asarray(rest_offsets_mm, np.float64)
    if offsets.shape != model.v_template.shape:
        raise ValueError(f"rest offsets: expected shape {model.v_template.shape}, got {offsets.shape}")
    return dataclasses.replace(model, v_template=model.v_template + offsets / scale)
