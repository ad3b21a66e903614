"""Writing one sequence of an SMPL ``Subject`` (e.g. a synthetic capture) in a capture dataset's own layout.

``export_capture(subject, out, fmt)`` writes the cameras, frames and SMPL parameters through the
``deliffas.io`` writers of ``fmt`` (``zju``, ``easymocap``, ``thuman4``, ``dna``, ``actorshq``), with
JPEG where the dataset stores JPEG. It exists so that each parser is tested on files written by
another code path; SMPL parameters are written in each dataset's own form (Rh/Th, SMPL-X, AMASS).
The SMPL model file is not copied (the datasets do not hold it; the parser takes it as ``--template``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np

from deliffas.io.formats.actorshq import actorshq_mask_path, actorshq_rgb_path, camera_to_actorshq, write_actorshq_calibration
from deliffas.io.body_models.amass import SMPL_BODY_POSE_DIM, write_smpl_motion
from deliffas.io.formats.capture_frames import write_image_file
from deliffas.io.formats.dna_rendering import SmcSmplx, cameras_to_smc, write_smc
from deliffas.io.formats.easymocap import EasyMocapSmpl, camera_to_easymocap, write_easymocap_cameras, write_easymocap_smpl
from deliffas.io.body_models.smpl import load_smpl_model
from deliffas.io.formats.thuman4 import (Thuman4Smplx, camera_to_thuman4, thuman4_image_path, thuman4_mask_path,
                                 write_thuman4_calibration, write_thuman4_smplx)
from deliffas.io.formats.zju_mocap import cameras_to_zju, write_zju_annots, write_zju_params, zju_params_path
from deliffas.geometry.smpl_params import params_to_motion, params_to_rhth, rest_root_joint
from deliffas.data.subjects import Subject

__all__ = ["ExportFormat", "EXPORT_FORMATS", "export_capture"]

ExportFormat = Literal["zju", "easymocap", "thuman4", "dna", "actorshq"]
EXPORT_FORMATS: tuple[str, ...] = ("zju", "easymocap", "thuman4", "dna", "actorshq")
"""Layouts ``export_capture`` writes (the parser registered under the same name reads them)."""


class _Frames:
    """The sequence's frames, SMPL rows (N, 3 + 72 + NB) and pixels, as the writers need them."""

    def __init__(self, subject: Subject, sequence: str):
        if subject.template.kind != "smpl":
            raise ValueError(f"export: needs an SMPL subject (its pose parameters are written), got {subject.template.kind}")
        seq = subject.sequences[sequence]
        if seq.poses is None:
            raise ValueError(f"export: sequence {sequence} has no SMPL pose parameters")
        self.cameras = subject.cameras
        self.frames = [int(f) for f in seq.frames]
        self.params = np.stack([seq.poses.dofs[seq.poses.row_of(f)] for f in self.frames])  # (N, D)
        self.betas = self.params[0, 3 + 72:]
        self.model_path = subject.template.path("model")
        self._spec = seq.images

    def pixels(self):
        """Yields (frame, camera index, rgb (H, W, 3), mask (H, W)) in frame-major order."""
        src = self._spec.open()
        try:
            for f in self.frames:
                for c in range(len(self.cameras)):
                    yield (f, c, *src.read(f, c))
        finally:
            src.close()

    def rhth(self):
        """(Rh, Th, poses) in EasyMocap's form for every frame."""
        root = rest_root_joint(load_smpl_model(self.model_path), self.betas)
        return params_to_rhth(self.params, root)

    def smplx_pose(self) -> np.ndarray:
        """(N, 55, 3) SMPL-X full pose with SMPL's 22 shared joints (SMPL hand joints are not SMPL-X joints)."""
        out = np.zeros((len(self.frames), 55, 3))
        out[:, :22] = self.params[:, 3:3 + SMPL_BODY_POSE_DIM].reshape(-1, 22, 3)
        return out


def _zju(fr: _Frames, out: Path, q: int) -> None:
    names = [f"Camera_B{c + 1}" for c in range(len(fr.cameras))]
    ims = [[f"{n}/{f:06d}.jpg" for n in names] for f in fr.frames]
    for f, c, rgb, mask in fr.pixels():
        write_image_file(out / names[c] / f"{f:06d}.jpg", rgb, q)
        write_image_file(out / "mask_cihp" / names[c] / f"{f:06d}.png", (mask >= 128).astype(np.uint8))  # 0/1
    write_zju_annots(out / "annots.npy", cameras_to_zju(fr.cameras, ims))
    Rh, Th, poses = fr.rhth()
    for i, f in enumerate(fr.frames):
        write_zju_params(zju_params_path(out, f), EasyMocapSmpl(0, Rh[i:i + 1], Th[i:i + 1], poses[i:i + 1],
                                                                fr.betas[None]))


def _easymocap(fr: _Frames, out: Path, q: int) -> None:
    write_easymocap_cameras(out, [camera_to_easymocap(c) for c in fr.cameras])
    for f, c, rgb, mask in fr.pixels():
        write_image_file(out / "images" / fr.cameras[c].name / f"{f:06d}.jpg", rgb, q)
        write_image_file(out / "mask" / fr.cameras[c].name / f"{f:06d}.png", mask)
    Rh, Th, poses = fr.rhth()
    for i, f in enumerate(fr.frames):
        write_easymocap_smpl(out / "output" / "smpl" / f"{f:06d}.json",
                             [EasyMocapSmpl(0, Rh[i:i + 1], Th[i:i + 1], poses[i:i + 1], fr.betas[None])])


def _thuman4(fr: _Frames, out: Path, q: int) -> None:
    if fr.frames != list(range(len(fr.frames))):
        raise ValueError(f"export thuman4: smpl_params.npz rows are frames 0..N-1, the sequence has {fr.frames[:5]}...")
    write_thuman4_calibration(out / "calibration.json", [camera_to_thuman4(c) for c in fr.cameras])
    for f, c, rgb, mask in fr.pixels():
        write_image_file(thuman4_image_path(out, fr.cameras[c].name, f), rgb, q)
        write_image_file(thuman4_mask_path(out, fr.cameras[c].name, f), mask, q)
    pose = fr.smplx_pose()
    write_thuman4_smplx(out / "smpl_params.npz", Thuman4Smplx(fr.betas[None], pose[:, 0], fr.params[:, :3],
                                                              pose[:, 1:22].reshape(len(pose), -1), {}))


def _dna(fr: _Frames, out: Path, q: int) -> None:
    if fr.frames != list(range(len(fr.frames))):
        raise ValueError(f"export dna: .smc frames are 0..N-1, the sequence has {fr.frames[:5]}...")
    calib = cameras_to_smc(fr.cameras)
    images = {c.camera_id: [] for c in calib}
    masks = {c.camera_id: [] for c in calib}
    for _, c, rgb, mask in fr.pixels():
        images[calib[c].camera_id].append(rgb)
        masks[calib[c].camera_id].append(mask)
    smplx = SmcSmplx(fr.betas[None], np.zeros((len(fr.frames), 10)), fr.smplx_pose(), fr.params[:, :3].copy())
    write_smc(out / f"{out.name}.smc", calib, images, masks, smplx, jpeg_quality=q)


def _actorshq(fr: _Frames, out: Path, q: int) -> None:
    write_actorshq_calibration(out / "calibration.csv", [camera_to_actorshq(c) for c in fr.cameras])
    for f, c, rgb, mask in fr.pixels():
        write_image_file(actorshq_rgb_path(out, fr.cameras[c].name, f), rgb, q)
        write_image_file(actorshq_mask_path(out, fr.cameras[c].name, f), mask)
    if fr.frames != list(range(len(fr.frames))):
        raise ValueError(f"export actorshq: poses.npz rows are frames 0..N-1, the sequence has {fr.frames[:5]}...")
    write_smpl_motion(out / "poses.npz", params_to_motion(fr.params))


_WRITERS = {"zju": _zju, "easymocap": _easymocap, "thuman4": _thuman4, "dna": _dna, "actorshq": _actorshq}


def export_capture(subject: Subject, out_dir: str | os.PathLike, fmt: ExportFormat, sequence: str = "training",
                   jpeg_quality: int = 95) -> Path:
    """Write ``sequence`` of an SMPL ``subject`` as a ``fmt`` capture folder; returns the folder.

    Raises:
        ValueError: an unknown format, a non-SMPL subject, or frames the layout cannot number.
        FileExistsError: ``out_dir`` exists and is not empty.
    """
    if fmt not in _WRITERS:
        raise ValueError(f"export: unknown capture format {fmt!r}; expected one of {', '.join(EXPORT_FORMATS)}")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out}: not empty; export writes a new capture folder")
    out.mkdir(parents=True, exist_ok=True)
    _WRITERS[fmt](_Frames(subject, sequence), out, int(jpeg_quality))
    return out
