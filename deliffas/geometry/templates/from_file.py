"""The template spec of a template file, chosen by its kind: ``.character`` (DDC) or an SMPL model file."""

from __future__ import annotations

import os
from pathlib import Path

from deliffas.geometry.templates.base import TemplateSpec
from deliffas.geometry.templates.ddc import Skinning, ddc_spec
from deliffas.geometry.templates.smpl import smpl_spec

__all__ = ["SMPL_MODEL_SUFFIXES", "spec_from_file"]

SMPL_MODEL_SUFFIXES = (".npz", ".pkl")
"""Suffixes of an SMPL model file."""


def spec_from_file(path: str | os.PathLike, skinning: Skinning = "dqs", num_betas: int = 10,
                   uv_obj: str | os.PathLike | None = None) -> TemplateSpec:
    """``ddc_spec`` of a ``.character``, or ``smpl_spec`` of an SMPL model file with its uv layout:
    ``uv_obj``, else ``<stem>_uv.obj`` next to the model when present (else an xatlas atlas).

    Raises:
        ValueError: another suffix (the message lists the accepted ones).
        FileNotFoundError: the file does not exist.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: template file not found")
    if p.suffix == ".character":
        return ddc_spec(p, skinning)
    if p.suffix in SMPL_MODEL_SUFFIXES:
        uv = Path(uv_obj) if uv_obj is not None else p.with_name(f"{p.stem}_uv.obj")
        return smpl_spec(p, uv if uv_obj is not None or uv.is_file() else None, num_betas=num_betas)
    raise ValueError(f"{p}: expected a .character (DDC) or an SMPL model ({', '.join(SMPL_MODEL_SUFFIXES)})")
