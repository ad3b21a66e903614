"""What ``fit_smpl_capture`` fits and writes (:class:`FitSmplConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from deliffas.geometry.smpl_surface_fit_config import SurfaceFitConfig
from deliffas.options import opt

__all__ = ["FitSmplConfig"]


@dataclass(frozen=True)
class FitSmplConfig:
    """SMPL fitted to every frame of a capture, written as motions
    (:func:`deliffas.data.smpl_capture_fit.fit_smpl_capture`)."""

    subject: Path = opt(help="capture folder", flag="")
    model: Path = opt(help="SMPL model .npz/.pkl (official layout; not shipped)")
    out: Path = opt(help="folder for the fitted motions (<sequence>.npz per sequence, fit.json)")
    uv: Path | None = opt(None, help="OBJ with the model's uv layout", default_text="MODEL_uv.obj if present")
    overwrite: bool = opt(False, help="replace an earlier fit in --out (a non-empty one is refused otherwise, before "
                                      "fitting)")
    fit: SurfaceFitConfig = field(default_factory=SurfaceFitConfig)
    """How each sequence is fitted (its own options)."""
