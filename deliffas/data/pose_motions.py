"""Reading a motion file as the per-frame pose parameters of a template (the ``Motion`` deliffas poses with).

Each template kind owns its motion files (``TemplateKind.motion_suffix`` and ``read_motion``): a DDC
template (``ddc``, ``ddc_graph``) takes a Skeletool ``.motion`` (DOF rows); an ``smpl`` template takes
an AMASS-style ``.npz`` (``poses``, ``trans``, ``betas``), turned into the template's rows
``[trans, pose (72), betas[:num_betas]]``. The file's kind must fit the template's.
"""

from __future__ import annotations

import os
from pathlib import Path

from deliffas.io.motion import Motion
from deliffas.geometry.templates import TemplateSpec, template_kind

__all__ = ["read_pose_motion", "motion_suffix"]


def motion_suffix(kind: str) -> str:
    """The motion file suffix of template ``kind``.

    Raises:
        ValueError: an unknown kind, or one without motion files.
    """
    suffix = template_kind(kind).motion_suffix
    if suffix is None:
        raise ValueError(f"no motion format is known for template kind {kind!r}")
    return suffix


def read_pose_motion(path: str | os.PathLike, spec: TemplateSpec, num_dofs: int | None = None) -> Motion:
    """The pose parameters of every frame of ``path`` for the template ``spec``.

    Args:
        num_dofs: the template's parameter count, checked against the file (DDC motions).

    Raises:
        ValueError: a motion file of another kind than the template takes, or one that breaks its format.
    """
    p = Path(path)
    kind = template_kind(spec.kind)
    if kind.motion_suffix is None or kind.read_motion is None:
        raise ValueError(f"{p}: no motion format is known for template kind {spec.kind!r}")
    if p.suffix.lower() != kind.motion_suffix:
        raise ValueError(f"{p}: a {spec.kind} template takes a {kind.motion_suffix} motion, got '{p.suffix}'")
    return kind.read_motion(p, spec, num_dofs)
