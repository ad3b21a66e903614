"""Posing a template by a motion file: the API behind ``deliffas pose``.

The template is a ``.character`` (DDC, with a ``.motion``) or an SMPL model file (with an AMASS-style
``.npz`` motion); frames are the frame numbers the motion file gives (row ``i`` of an AMASS file is
frame ``i``).

This is posing's numpy boundary: templates are torch modules (``Template.pose`` takes and returns
tensors); ``pose_frames`` reads files, poses in torch and returns numpy vertices.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float, Real

from deliffas.io.motion import Motion
from deliffas.io.mesh_files import write_mesh
from deliffas.io.infra.files import claim_output_file
from deliffas.geometry.templates import Skinning, Template, TemplateSpec, build_template, spec_from_file
from deliffas.data.pose_config import PoseConfig
from deliffas.data.pose_motions import read_pose_motion

__all__ = ["pose_frames", "write_posed_mesh", "PoseConfig", "PosedMesh", "pose_to_file"]


def pose_frames(template: TemplateSpec | str | os.PathLike, motion: Motion | str | os.PathLike,
                frames: list[int] | None = None, skinning: Skinning = "dqs",
                dtype: torch.dtype = torch.float64) -> tuple[Float[np.ndarray, "N V 3"], Template]:
    """Posed vertices of ``template`` for the given frame numbers of ``motion``.

    Args:
        template: a spec, or a template file (``.character`` or SMPL model, :func:`spec_from_file`).
        motion: pose parameters, or a motion file of the template's kind.
        frames: frame numbers as written in the motion file (not row numbers); None = all frames.
        skinning: a DDC template's skinning (when ``template`` is a file).
        dtype: the precision the template poses in, and the dtype of the returned vertices.

    Returns:
        verts (N, V, 3) numpy mm in template vertex order, of ``dtype`` (float64 by default), and
        the template.

    Raises:
        ValueError: a frame the motion lacks, a motion of another kind or size, or non-finite output.
    """
    spec = template if isinstance(template, TemplateSpec) else spec_from_file(template, skinning)
    posable = build_template(spec, dtype=dtype)
    if not isinstance(motion, Motion):
        motion = read_pose_motion(motion, spec, posable.num_dofs)
    elif motion.dofs.shape[1] != posable.num_dofs:
        raise ValueError(f"motion has {motion.dofs.shape[1]} values per frame, the template takes {posable.num_dofs}")
    if frames is None:
        rows = np.arange(motion.num_frames)
    else:
        try:
            rows = np.array([motion.row_of(f) for f in frames])
        except KeyError as err:
            raise ValueError(str(err.args[0])) from None
    with torch.no_grad():
        verts = posable.pose(torch.as_tensor(motion.dofs[rows], dtype=dtype)).cpu().numpy()
    if not np.isfinite(verts).all():
        raise ValueError(f"posing gave non-finite vertices (frames {[int(f) for f in motion.frames[rows]][:5]}); "
                         "check the motion's values")
    return verts, posable


def write_posed_mesh(path: str | os.PathLike, verts: Real[np.ndarray, "V 3"], template: Template) -> Path:
    """Write one posed mesh as ``.obj`` (with the template's per-corner uvs) or ``.ply``, template order."""
    return write_mesh(path, verts, template.faces.cpu().numpy(), template.uvs.cpu().numpy(),
                      template.face_uvs.cpu().numpy())


@dataclass(frozen=True)
class PosedMesh:
    """What :func:`pose_to_file` wrote."""

    path: Path
    num_verts: int
    num_faces: int
    kind: str
    """The template kind (``TemplateSpec.kind``)."""
    skinning: str | None
    """A DDC template's skinning; None for kinds without the option."""


def pose_to_file(config: PoseConfig) -> PosedMesh:
    """Pose ``config.template`` by frame ``config.frame`` of ``config.motion`` and write the mesh to ``config.out``
    (refused when it exists, unless ``config.overwrite``)."""
    claim_output_file(config.out, config.overwrite)
    spec = spec_from_file(config.template, config.skinning, uv_obj=config.uv)
    verts, template = pose_frames(spec, config.motion, [config.frame], config.skinning)
    path = write_posed_mesh(config.out, verts[0], template)
    return PosedMesh(Path(path), int(verts.shape[1]), int(template.faces.shape[0]), spec.kind, spec.option("skinning"))
