"""The ``dynacap`` capture format: a DynaCap / DELIFFAS subject folder (layout in docs/data.md).

``<subject>/cameras.calibration``, the template: ``character/<name>.character`` (DDC) or
``body/<model>.npz`` with ``body/<model>_uv.obj`` (SMPL), or ``--template``; and per sequence
(``training``, ``testing``) the frames (``rgb_<W>_<H>/`` image folders or ``img/`` + ``fg/`` videos)
and the pose parameters: ``poses.motion`` for a DDC template, AMASS-style ``poses.npz`` for SMPL
(or ``motions/*``, or ``--motions [SEQ=]FILE``), or a tracked ``.meshes`` given by the user.
The test cameras come from ``split.json`` (``test_cameras``) or ``test_cameras.txt``. DynaCap is
already in the deliffas convention (mm, y-up, world -> camera, pixel centres at +0.5).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.format_registry import CaptureFormat, register_capture_format
from deliffas.io.formats.dynacap.calibration import read_calibration
from deliffas.io.formats.dynacap.meshes import read_meshes
from deliffas.io.formats.dynacap.frames import image_size
from deliffas.geometry.templates import SMPL_MODEL_SUFFIXES, Skinning, TemplateSpec, ddc_spec, spec_from_file
from deliffas.data.pose_motions import motion_suffix, read_pose_motion
from deliffas.data.subjects.capture_common import read_test_cameras
from deliffas.data.subjects.base import (
    FrameSourceSpec,
    Subject,
    SubjectOptions,
    SubjectSequence,
)

__all__ = ["SEQUENCES", "find_character", "find_template", "parse_dynacap"]

SEQUENCES = ("training", "testing")


def find_character(subject: Path, template: str | None) -> tuple[Path, Path | None]:
    """The ``.character`` to use and a variant's ``outer.obj`` (or None)."""
    if template is not None:
        t = Path(template)
        if t.is_file() and t.suffix == ".character":
            outer = t.parent / "outer.obj"
            return t, outer if outer.is_file() else None
        found = sorted(t.glob("*.character")) if t.is_dir() else []
        if len(found) != 1:
            raise FileNotFoundError(f"--template {t}: expected a folder with one .character, found {len(found)}")
        outer = t / "outer.obj"
        return found[0], outer if outer.is_file() else None
    for d in (subject / "character", subject):
        found = sorted(d.glob("*.character")) if d.is_dir() else []
        if len(found) == 1:
            return found[0], None
        if len(found) > 1:
            raise FileNotFoundError(f"{d}: several .character files {[p.name for p in found]}; pass --template")
    raise FileNotFoundError(f"{subject}: no character/<name>.character; pass --template")


def find_template(subject: Path, template: str | None, skinning: Skinning = "dqs",
                  num_betas: int = 10) -> TemplateSpec:
    """The subject's template: ``template`` (a DDC variant folder or ``.character``, or an SMPL model
    file), else ``character/<name>.character``, else the one SMPL model in ``body/``."""
    if template is not None and Path(template).suffix in SMPL_MODEL_SUFFIXES:
        return spec_from_file(template, num_betas=num_betas)
    body = subject / "body"
    models = sorted(p for p in body.iterdir() if p.suffix in SMPL_MODEL_SUFFIXES) if body.is_dir() else []
    if template is None and not (subject / "character").is_dir() and models:
        if len(models) > 1:
            raise FileNotFoundError(f"{body}: several SMPL model files {[p.name for p in models]}; pass --template")
        return spec_from_file(models[0], num_betas=num_betas)
    character, outer_obj = find_character(subject, template)
    return ddc_spec(character, skinning, outer_obj)


def _find_motion(seq_dir: Path, suffix: str) -> Path | None:
    p = seq_dir / f"poses{suffix}"
    if p.is_file():
        return p
    found = sorted((seq_dir / "motions").glob(f"*{suffix}")) if (seq_dir / "motions").is_dir() else []
    return found[0] if found else None


def _per_sequence(specs: Sequence[str], option: str) -> dict[str, Path]:
    """``[SEQUENCE=]FILE`` values (default sequence: training) by sequence."""
    out = {}
    for s in specs:
        seq, sep, path = s.partition("=")
        if not sep:
            seq, path = "training", s
        if seq in out:
            raise ValueError(f"--{option} given twice for sequence {seq}")
        out[seq] = Path(path).resolve()
    return out


def parse_dynacap(subject: Path, options: SubjectOptions = SubjectOptions()) -> Subject:
    """Read a DynaCap subject folder into a :class:`Subject` (pose parameters = the motions' DOFs)."""
    subject = Path(subject)
    cameras = tuple(read_calibration(subject / "cameras.calibration"))
    names = tuple(c.name for c in cameras)
    template = find_template(subject, options.template, options.skinning)
    meshes = _per_sequence(options.meshes, "meshes")
    motions = _per_sequence(options.motions, "motions")
    seq_names = options.sequences or tuple(s for s in SEQUENCES if (subject / s).is_dir())
    if not seq_names:
        raise FileNotFoundError(f"{subject}: no training/ or testing/ sequence folder")
    sequences: dict[str, SubjectSequence] = {}
    size = None
    for seq in seq_names:
        seq_dir = subject / seq
        if not seq_dir.is_dir():
            raise FileNotFoundError(f"{seq_dir}: sequence folder not found")
        w, h, layout = image_size(seq_dir, options.layout, names)
        if size is not None and size != (w, h):
            raise ValueError(f"{seq}: images are {w}x{h}, other sequences {size[0]}x{size[1]}")
        size = (w, h)
        motion_path = motions.get(seq) or _find_motion(seq_dir, motion_suffix(template.kind))
        motion = read_pose_motion(motion_path, template) if motion_path is not None else None
        mesh_path = meshes.get(seq)
        if mesh_path is not None:
            avail = read_meshes(mesh_path).frames
        elif motion is not None:
            avail = motion.frames
        else:
            raise FileNotFoundError(f"{seq_dir}: no poses{motion_suffix(template.kind)} (and no --motions or "
                                    f"--meshes {seq}=FILE)")
        avail = np.unique(np.asarray(avail, np.int64))
        first = int(avail.min())
        mask_dir = seq_dir / options.masks if options.masks else None
        images = FrameSourceSpec(seq_dir, names, layout, first, mask_dir)
        sequences[seq] = SubjectSequence(seq, avail, first, w, h, images, motion, mesh_path)
    return Subject(subject, "dynacap", cameras, template, sequences, read_test_cameras(subject, options.test_cameras))


def _is_dynacap(folder: Path) -> bool:
    return (folder / "cameras.calibration").is_file()


register_capture_format(CaptureFormat("dynacap", detect_subject=_is_dynacap, parse_subject=parse_dynacap))
