"""The ``actorshq`` capture format: an ActorsHQ sequence folder (HumanRF's layout) as a Subject.

Reads ``calibration.csv`` (camera -> world axis-angle, metres, normalised intrinsics, deliffas pixel
centres, radial k1 k2 k3 undone when frames are read), ``rgbs/<cam>/<cam>_rgb<frame:06d>.jpg`` and
``masks/<cam>/<cam>_mask<frame:06d>.png``. ActorsHQ ships **no body-model parameters**: the surface
comes from an SMPL fit given as an AMASS-style ``--motions [training=]POSES.npz`` (row k = frame k;
``poses.npz`` in the folder is used when present) with ``--template SMPL.npz``, or from tracked
``--meshes training=FILE.meshes`` with the matching ``--template``. Without either it cannot be converted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deliffas.io.body_models.amass import write_smpl_motion
from deliffas.io.format_registry import CaptureFormat, register_capture_format
from deliffas.io.formats.actorshq import (actorshq_mask_path, actorshq_rgb_path, actorshq_to_camera, camera_to_actorshq,
                                          read_actorshq_calibration, write_actorshq_calibration)
from deliffas.io.formats.capture_frames import FileFramesSpec, write_image_file
from deliffas.io.formats.dynacap.meshes import read_meshes
from deliffas.geometry.smpl_params import params_to_motion
from deliffas.geometry.templates import template_kind
from deliffas.data.subjects.base import Subject, SubjectOptions, SubjectSequence
from deliffas.data.subjects.export_frames import ExportFrames
from deliffas.data.subjects.capture_common import (SEQUENCE, read_test_cameras, require_template, split_distortion,
                                                   user_motion)

__all__ = ["parse_actorshq", "export_actorshq"]


def _meshes(options: SubjectOptions) -> Path | None:
    for s in options.meshes:
        seq, sep, path = s.partition("=")
        if not sep or seq == SEQUENCE:
            return Path(path if sep else s)
    return None


def parse_actorshq(root: Path, options: SubjectOptions = SubjectOptions()) -> Subject:
    """Read an ActorsHQ sequence folder (see the module docstring)."""
    root = Path(root)
    records = read_actorshq_calibration(root / "calibration.csv")
    cameras, undistort = split_distortion([actorshq_to_camera(c, root / "calibration.csv") for c in records],
                                          "ActorsHQ")
    names = [c.name for c in records]
    meshes = _meshes(options)
    motion = user_motion(options, root / "poses.npz")
    if motion is None and meshes is None:
        raise ValueError(f"{root}: ActorsHQ has no body-model parameters; pass an SMPL fit (--motions "
                         "training=POSES.npz --template SMPL.npz) or tracked surfaces (--meshes training=FILE.meshes "
                         "--template ...)")
    spec = require_template(options, "ActorsHQ")
    if motion is not None and not template_kind(spec.kind).smpl_params:
        raise ValueError(f"{root}: an AMASS-style SMPL motion needs an SMPL --template, got a {spec.kind} template")
    avail = read_meshes(meshes).frames if meshes is not None else motion.frames
    frames = [int(f) for f in np.unique(avail)
              if all(actorshq_rgb_path(root, n, int(f)).is_file() for n in names)]
    if not frames:
        raise FileNotFoundError(f"{root / 'rgbs'}: no frame with a surface has rgbs/<cam>/<cam>_rgb<frame:06d>.jpg "
                                "in every camera")
    images = {f: tuple(str(actorshq_rgb_path("", n, f)) for n in names) for f in frames}
    have_masks = all(actorshq_mask_path(root, n, frames[0]).is_file() for n in names)
    masks = {f: tuple(str(actorshq_mask_path("", n, f)) for n in names) for f in frames} if have_masks else None
    source = FileFramesSpec(root, images, masks, "gray", undistort)
    seq = SubjectSequence(SEQUENCE, np.asarray(frames, np.int64), frames[0], cameras[0].width, cameras[0].height,
                          source, motion, meshes)
    return Subject(root, "actorshq", cameras, spec, {SEQUENCE: seq}, read_test_cameras(root, options.test_cameras))


def export_actorshq(fr: ExportFrames, out: Path, q: int) -> None:
    """Write ``fr`` as an ActorsHQ folder: ``calibration.csv``, rgbs, masks, ``poses.npz`` (AMASS-style)."""
    write_actorshq_calibration(out / "calibration.csv", [camera_to_actorshq(c) for c in fr.cameras])
    for f, c, rgb, mask in fr.pixels():
        write_image_file(actorshq_rgb_path(out, fr.cameras[c].name, f), rgb, q)
        write_image_file(actorshq_mask_path(out, fr.cameras[c].name, f), mask)
    fr.require_frames_from_zero("actorshq", "poses.npz")
    write_smpl_motion(out / "poses.npz", params_to_motion(fr.params))


register_capture_format(CaptureFormat("actorshq", detect_subject=lambda root: (root / "calibration.csv").is_file(),
                                      parse_subject=parse_actorshq, export=export_actorshq))
