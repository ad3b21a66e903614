"""The ``smpl`` template kind: SMPL posed by ``[transl, axis-angle pose, betas]`` from a user's model file.

SMPL is not shipped (license): the user passes the path of an official-layout model file
(:func:`deliffas.io.body_models.smpl.load_smpl_model`). SMPL is in metres; ``scale=1000`` (default) puts vertices
and translations in the mm world of deliffas. The maths are :mod:`deliffas.geometry.smpl`; this
module only holds the model's arrays as buffers.
"""

from __future__ import annotations

import dataclasses
import logging
import os

import numpy as np
import torch
from torch import nn
from jaxtyping import Float
from torch import Tensor

from deliffas.checks import check_finite, check_shape
from deliffas.io.obj import read_obj
from deliffas.io.body_models.amass import read_smpl_motion, write_smpl_motion
from deliffas.io.body_models.smpl import NUM_JOINTS, NUM_POSE_BASIS, SMPLModelData, SMPLModelError, load_smpl_model
from deliffas.geometry.arrays import require_tensor
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.smpl import smpl_lbs
from deliffas.geometry.smpl_params import params_to_motion, smpl_to_motion
from deliffas.geometry.templates.base import TemplateKind, TemplateSpec, make_spec, register_template_kind

__all__ = ["SMPLTemplate", "smpl_spec", "read_smpl_rows", "write_smpl_rows"]

log = logging.getLogger(__name__)


class SMPLTemplate(nn.Module):
    """SMPL posed by ``params = [transl (3), axis-angle pose (72), betas (num_betas)]``.

    Args:
        model: path of the user's model file (.npz / .pkl) or loaded ``SMPLModelData``.
        num_betas: shape coefficients used (<= the model's).
        scale: model units -> world units; 1000 maps SMPL metres to mm (translations too).
        uv_obj: optional OBJ with the SMPL UV layout (same faces, per-corner ``vt``); without it a
            new xatlas atlas is made (``deliffas.geometry.atlas``).
        atlas_res: xatlas packing resolution when no ``uv_obj`` is given.
        dtype: buffer dtype.
    """

    def __init__(self, model: str | os.PathLike | SMPLModelData, num_betas: int = 10, scale: float = 1000.0,
                 uv_obj: str | os.PathLike | None = None, atlas_res: int = 1024, dtype: torch.dtype = torch.float32):
        super().__init__()
        data = model if isinstance(model, SMPLModelData) else load_smpl_model(model)
        if not 0 <= num_betas <= data.num_betas:
            raise ValueError(f"num_betas: expected 0..{data.num_betas} (the model's), got {num_betas}")
        self.num_betas = int(num_betas)
        self.scale = float(scale)
        V = data.num_verts
        self.register_buffer("v_template", torch.tensor(data.v_template * scale, dtype=dtype))
        self.register_buffer("shapedirs", torch.tensor(data.shapedirs[:, :, :num_betas] * scale, dtype=dtype))
        posedirs = (data.posedirs * scale).reshape(V * 3, NUM_POSE_BASIS).T  # (207, V * 3)
        self.register_buffer("posedirs", torch.tensor(np.ascontiguousarray(posedirs), dtype=dtype))
        self.register_buffer("J_regressor", torch.tensor(data.J_regressor, dtype=dtype))
        self.register_buffer("lbs_weights", torch.tensor(data.weights, dtype=dtype))
        self.register_buffer("parents", torch.as_tensor(data.parents, dtype=torch.long))
        self.register_buffer("faces", torch.as_tensor(data.faces, dtype=torch.long))
        uvs, face_uvs = self._uvs(data, uv_obj, atlas_res)
        self.register_buffer("uvs", torch.tensor(uvs, dtype=dtype))
        self.register_buffer("face_uvs", torch.as_tensor(face_uvs, dtype=torch.long))

    def _uvs(self, data: SMPLModelData, uv_obj, atlas_res: int) -> tuple[np.ndarray, np.ndarray]:
        if uv_obj is not None:
            obj = read_obj(uv_obj)
            if not obj.has_uvs or obj.num_faces != len(data.faces):
                raise SMPLModelError(f"{uv_obj}: expected {len(data.faces)} faces with per-corner uvs, "
                                     f"got {obj.num_faces} faces (uvs {'present' if obj.has_uvs else 'absent'})")
            if not np.array_equal(obj.faces, data.faces):
                raise SMPLModelError(f"{uv_obj}: its face list differs from the model's 'f'")
            return np.array(obj.uvs), np.array(obj.face_uvs)
        log.info("SMPLTemplate: no uv_obj given, computing an xatlas atlas for %d faces", len(data.faces))
        atlas = UVAtlas.from_mesh(data.v_template, data.faces, resolution=atlas_res)
        return np.array(atlas.uvs), np.array(atlas.face_uvs)

    @property
    def num_verts(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def rest_verts(self) -> torch.Tensor:
        """(V, 3) the mean-shape template, world units."""
        return self.v_template

    @property
    def num_dofs(self) -> int:
        """3 (translation) + 72 (pose) + num_betas."""
        return 3 + 3 * NUM_JOINTS + self.num_betas

    def rest_params(self, batch: int = 1) -> Float[Tensor, "B D"]:
        """(B, num_dofs) zeros: the T-pose with mean shape at the origin."""
        return torch.zeros(batch, self.num_dofs, dtype=self.v_template.dtype, device=self.v_template.device)

    def pose_with_joints(self, params: Float[Tensor, "B D"]) -> tuple[Float[Tensor, "B V 3"], Float[Tensor, "B 24 3"]]:
        """Vertices (B, V, 3) and joints (B, 24, 3), world units (mm with the default scale), in the
        template's dtype and on its device (torch-only: numpy motions go through ``deliffas.data.posing``)."""
        require_tensor("params", params, "torch.as_tensor(params), or deliffas.data.posing.pose_frames for numpy")
        check_shape("params", params, "B D", {"D": self.num_dofs})
        check_finite("params", params)
        params = params.to(self.v_template)
        transl = params[:, :3] * self.scale
        pose = params[:, 3:3 + 3 * NUM_JOINTS]
        betas = params[:, 3 + 3 * NUM_JOINTS:]
        verts, joints = smpl_lbs(betas, pose, self.v_template, self.shapedirs, self.posedirs, self.J_regressor,
                                 self.parents, self.lbs_weights)
        return verts + transl[:, None], joints + transl[:, None]

    def pose(self, params: Float[Tensor, "B D"]) -> Float[Tensor, "B V 3"]:
        """(B, 3 + 72 + num_betas) [transl (model units), axis-angle pose, betas] -> (B, V, 3) vertices."""
        return self.pose_with_joints(params)[0]

    def forward(self, params: Float[Tensor, "B D"]) -> Float[Tensor, "B V 3"]:
        return self.pose(params)


def smpl_spec(model_path: str | os.PathLike, uv_obj: str | os.PathLike | None = None, num_betas: int = 10,
              scale: float = 1000.0, atlas_res: int = 1024) -> TemplateSpec:
    """The ``smpl`` spec of a model file (and an optional OBJ with its uv layout)."""
    return make_spec("smpl", {"model": model_path, "uv_obj": uv_obj}, num_betas=int(num_betas), scale=float(scale),
                     atlas_res=int(atlas_res))


def _build(spec: TemplateSpec, dtype: torch.dtype) -> SMPLTemplate:
    uv_obj = spec.files.get("uv_obj")
    return SMPLTemplate(spec.path("model"), num_betas=spec.option("num_betas", 10), scale=spec.option("scale", 1000.0),
                        uv_obj=uv_obj, atlas_res=spec.option("atlas_res", 1024), dtype=dtype)


def read_smpl_rows(path, spec: TemplateSpec, num_dofs: int | None = None):
    """An AMASS-style ``.npz`` motion as the template's rows ``[trans, pose (72), betas[:num_betas]]``."""
    return smpl_to_motion(read_smpl_motion(path), int(spec.option("num_betas", 10)))


def write_smpl_rows(path, motion, fps: float) -> None:
    """SMPL rows written as an AMASS-style ``.npz`` (with the deliffas ``frames`` key when they are not 0..N-1)."""
    out = params_to_motion(motion.dofs, fps=fps)
    frames = np.asarray(motion.frames, np.int64)
    if not np.array_equal(frames, np.arange(len(frames))):
        out = dataclasses.replace(out, frames=frames)
    write_smpl_motion(path, out)


register_template_kind(TemplateKind("smpl", _build, ".npz", read_smpl_rows, write_smpl_rows, smpl_params=True))
