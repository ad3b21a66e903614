"""Reading a motion file as the per-frame pose parameters of a template (the ``Motion`` deliffas poses with).

A DDC template (``ddc``, ``ddc_graph``) takes a Skeletool ``.motion`` (DOF rows); an ``smpl`` template
takes an AMASS-style ``.npz`` (``poses``, ``trans``, ``betas``), turned into the template's rows
``[trans, pose (72), betas[:num_betas]]``. The file's kind must fit the template's.
"""

from __future__ import annotations

import os
from pathlib import Path

from deliffas.io.body_models.amass import read_smpl_motion
from deliffas.io.formats.dynacap.character import read_motion
from deliffas.io.motion import Motion
from deliffas.geometry.smpl_params import smpl_to_motion
from deliffas.geometry.templates import TemplateSpec

__all__ = ["read_pose_motion", "MOTION_SUFFIXES"]

MOTION_SUFFIXES = {"ddc": ".motion", "ddc_graph": ".motion", "smpl": ".npz"}
"""The motion file suffix of each template kind."""


def read_pose_motion(path: str | os.PathLike, spec: TemplateSpec, num_dofs: int | None = None) -> Motion:
    """The pose parameters of every frame of ``path`` for the template ``spec``.

    Args:
        num_dofs: the template's parameter count, checked against the file (DDC motions).

    Raises:
        ValueError: a motion file of another kind than the template takes, or one that breaks its format.
    """
    p = Path(path)
    expected = MOTION_SUFFIXES.get(spec.kind)
    if expected is None:
        raise ValueError(f"{p}: no motion format is known for template kind {spec.kind!r}")
    if p.suffix.lower() != expected:
        raise ValueError(f"{p}: a {spec.kind} template takes a {expected} motion, got '{p.suffix}'")
    if spec.kind == "smpl":
        return smpl_to_motion(read_smpl_motion(p), int(spec.option("num_betas", 10)))
    return read_motion(p, num_dofs=num_dofs)
