"""The ``thuman4`` capture format: a THuman4.0 / AvatarReX subject folder as a Subject.

Reads ``calibration.json`` (or ``calibration_full.json``; metres, world -> camera, OpenCV pixel
centres), images ``images/<cam>/<frame:08d>.jpg``, masks ``masks/<cam>/<frame:08d>.jpg`` (grey
values kept) and ``smpl_params.npz`` (SMPL-X, row f = frame f). SMPL-X -> SMPL: global orientation,
the 21 body joints and ``transl`` are copied (the same meaning in both models); SMPL's hand joints
are zero; jaw, eyes, fingers and expression are dropped; the first 10 betas are used in the SMPL
model's shape space, which is exact only when the capture was fitted with that SMPL model (an SMPL-X
fit posed through SMPL differs by the models' shape spaces). Needs the SMPL model file (``--template``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deliffas.io.format_registry import CaptureFormat, register_capture_format
from deliffas.io.formats.capture_frames import FileFramesSpec, write_image_file
from deliffas.io.formats.thuman4 import (Thuman4Smplx, camera_to_thuman4, read_thuman4_calibration, read_thuman4_smplx,
                                          thuman4_image_path, thuman4_mask_path, thuman4_to_camera,
                                          write_thuman4_calibration, write_thuman4_smplx)
from deliffas.io.motion import Motion
from deliffas.geometry.smpl_params import smplx_to_smpl_pose
from deliffas.data.subjects.base import Subject, SubjectOptions, SubjectSequence
from deliffas.data.subjects.export_frames import ExportFrames
from deliffas.data.subjects.capture_common import SEQUENCE, fit_betas, read_test_cameras, smpl_template, split_distortion

__all__ = ["parse_thuman4", "export_thuman4"]


def _calibration(root: Path) -> Path:
    for name in ("calibration.json", "calibration_full.json"):
        if (root / name).is_file():
            return root / name
    raise FileNotFoundError(f"{root}: no calibration.json (or calibration_full.json)")


def parse_thuman4(root: Path, options: SubjectOptions = SubjectOptions()) -> Subject:
    """Read a THuman4.0 subject folder (see the module docstring)."""
    root = Path(root)
    records = read_thuman4_calibration(_calibration(root))
    cameras, undistort = split_distortion([thuman4_to_camera(c) for c in records], "THuman4.0")
    spec = smpl_template(options, "THuman4.0")
    smplx = read_thuman4_smplx(root / "smpl_params.npz")
    names = [c.name for c in records]
    frames = [f for f in range(smplx.num_frames)
              if all((root / "images" / n / f"{f:08d}.jpg").is_file() for n in names)]
    if not frames:
        raise FileNotFoundError(f"{root / 'images'}: no frame of smpl_params.npz has images/<cam>/<frame:08d>.jpg "
                                "in every camera")
    rows = np.asarray(frames)
    betas = fit_betas(smplx.betas[0], str(root / "smpl_params.npz"))
    dofs = np.concatenate([smplx.transl[rows], smplx_to_smpl_pose(smplx.global_orient[rows], smplx.body_pose[rows]),
                           np.tile(betas, (len(rows), 1))], axis=1)
    motion = Motion(rows.astype(np.int64), dofs)
    images = {f: tuple(f"images/{n}/{f:08d}.jpg" for n in names) for f in frames}
    have_masks = all((root / "masks" / n / f"{frames[0]:08d}.jpg").is_file() for n in names)
    masks = {f: tuple(f"masks/{n}/{f:08d}.jpg" for n in names) for f in frames} if have_masks else None
    w, h = cameras[0].width, cameras[0].height
    source = FileFramesSpec(root, images, masks, "gray", undistort)
    seq = SubjectSequence(SEQUENCE, motion.frames, frames[0], w, h, source, motion)
    return Subject(root, "thuman4", cameras, spec, {SEQUENCE: seq}, read_test_cameras(root, options.test_cameras))


def _is_thuman4(root: Path) -> bool:
    return (root / "smpl_params.npz").is_file() and any((root / n).is_file()
                                                        for n in ("calibration.json", "calibration_full.json"))


def export_thuman4(fr: ExportFrames, out: Path, q: int) -> None:
    """Write ``fr`` as a THuman4.0 folder: ``calibration.json``, images, masks, ``smpl_params.npz`` (SMPL-X)."""
    fr.require_frames_from_zero("thuman4", "smpl_params.npz")
    write_thuman4_calibration(out / "calibration.json", [camera_to_thuman4(c) for c in fr.cameras])
    for f, c, rgb, mask in fr.pixels():
        write_image_file(thuman4_image_path(out, fr.cameras[c].name, f), rgb, q)
        write_image_file(thuman4_mask_path(out, fr.cameras[c].name, f), mask, q)
    pose = fr.smplx_pose()
    write_thuman4_smplx(out / "smpl_params.npz", Thuman4Smplx(fr.betas[None], pose[:, 0], fr.params[:, :3],
                                                              pose[:, 1:22].reshape(len(pose), -1), {}))


register_capture_format(CaptureFormat("thuman4", detect_subject=_is_thuman4, parse_subject=parse_thuman4,
                                      export=export_thuman4))
