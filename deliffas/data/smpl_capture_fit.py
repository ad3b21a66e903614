"""SMPL fitted to a capture frame by frame: the per-frame SMPL parameters of a capture made with another
template (e.g. a DDC character), written as AMASS-style motions that ``convert --motions`` takes.

For each sequence, every frame's surface (the capture's posed template, or its tracked ``.meshes``) is
the target of :func:`deliffas.geometry.smpl_surface_fit.fit_smpl_to_surfaces`; the result keeps the
capture's frame numbers (``frames`` key), so ``convert SUBJECT OUT --template MODEL.npz --motions
training=FIT/training.npz --motions testing=FIT/testing.npz`` converts the same images with SMPL.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from deliffas.io.body_models.amass import write_smpl_motion
from deliffas.io.infra.files import claim_output
from deliffas.io.formats.dynacap.meshes import read_meshes
from deliffas.io.infra.text_lines import write_text_atomic
from deliffas.geometry.smpl_params import params_to_motion
from deliffas.geometry.smpl_surface_fit import SurfaceFitConfig, fit_smpl_to_surfaces
from deliffas.geometry.templates import build_template, spec_from_file
from deliffas.data.fit_smpl_config import FitSmplConfig
from deliffas.data.subjects import Subject, parse_subject

__all__ = ["SMPLCaptureFit", "fit_smpl_to_subject", "write_fit", "FitSmplConfig", "fit_smpl_capture"]


@dataclass(frozen=True)
class SMPLCaptureFit:
    """The fitted motions of a capture and how well each frame fits.

    Attributes:
        motions: sequence name -> AMASS-style motion (metres, the capture's world, ``frames`` set).
        residual_mm: sequence name -> (N,) mean symmetric surface distance per frame, mm.
        model: the SMPL model file the motions are for.
    """

    motions: dict
    residual_mm: dict
    model: Path


def _surfaces(subject: Subject, name: str) -> np.ndarray:
    """(N, V, 3) mm surface of every frame of a sequence: tracked meshes, else the posed template."""
    seq = subject.sequences[name]
    if seq.surfaces is not None:
        meshes = read_meshes(seq.surfaces)
        index = {int(f): i for i, f in enumerate(meshes.frames)}
        return np.stack([meshes.verts[index[int(f)]] for f in seq.frames]).astype(np.float64)
    if seq.poses is None:
        raise ValueError(f"{subject.root}: sequence {name} has neither pose parameters nor tracked meshes")
    template = build_template(subject.template, dtype=torch.float64)
    rows = [seq.poses.row_of(int(f)) for f in seq.frames]
    with torch.no_grad():
        return template.pose(torch.as_tensor(seq.poses.dofs[rows])).numpy()


def fit_smpl_to_subject(subject: Subject, model: str | os.PathLike, uv_obj: str | os.PathLike | None = None,
                        num_betas: int = 10, sequences: tuple[str, ...] | None = None,
                        config: SurfaceFitConfig = SurfaceFitConfig()) -> SMPLCaptureFit:
    """Fit ``model`` (an SMPL model file) to every frame of the subject's sequences (default: all)."""
    spec = spec_from_file(model, num_betas=num_betas, uv_obj=uv_obj)
    smpl = build_template(spec, dtype=torch.float32)  # float32: the fit needs mm, not bits; 2-3x faster
    motions, residual = {}, {}
    for name in sequences or tuple(subject.sequences):
        if name not in subject.sequences:
            raise ValueError(f"{subject.root}: no sequence {name!r} (has {list(subject.sequences)})")
        fit = fit_smpl_to_surfaces(smpl, list(_surfaces(subject, name)), config)
        motion = params_to_motion(fit.params)
        motions[name] = type(motion)(motion.poses, motion.trans, motion.betas, motion.fps, motion.gender,
                                     np.asarray(subject.sequences[name].frames, np.int64))
        residual[name] = fit.residual_mm
    return SMPLCaptureFit(motions, residual, Path(model))


def write_fit(out_dir: str | os.PathLike, fit: SMPLCaptureFit, overwrite: bool = False) -> Path:
    """Write ``<out>/<sequence>.npz`` per sequence and ``fit.json`` (residuals, model); returns ``out``."""
    out = claim_output(out_dir, overwrite, "fit.json", "an SMPL fit")
    for name, motion in fit.motions.items():
        write_smpl_motion(out / f"{name}.npz", motion)
    report = {"model": str(fit.model), "sequences": {
        name: {"frames": int(len(r)), "residual_mm_mean": float(np.mean(r)), "residual_mm_max": float(np.max(r))}
        for name, r in fit.residual_mm.items()}}
    write_text_atomic(out / "fit.json", json.dumps(report, indent=2) + "\n")  # last: marks a finished fit
    return out


def fit_smpl_capture(config: FitSmplConfig) -> tuple[SMPLCaptureFit, Path]:
    """:func:`fit_smpl_to_subject` of ``config.subject`` (every sequence), written by :func:`write_fit` into
    ``config.out``; a non-empty ``out`` is refused before any fitting unless ``config.overwrite``.

    Returns:
        The fit and the folder written.
    """
    out = Path(config.out)
    if out.is_dir() and any(out.iterdir()) and not config.overwrite:
        raise FileExistsError(f"{out}: not empty; pass --overwrite to replace an earlier fit there")
    fit = fit_smpl_to_subject(parse_subject(config.subject), config.model, config.uv, config=config.fit)
    return fit, write_fit(out, fit, overwrite=config.overwrite)
