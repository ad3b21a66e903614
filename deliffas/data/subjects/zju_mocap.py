"""The ``zju`` capture format: a ZJU-MoCap subject folder (``CoreView_<id>``, Neural Body's layout) as a Subject.

Reads ``annots.npy`` (cameras, millimetres, world -> camera; image paths per frame), the masks
``mask_cihp/<image path>.png`` (else ``mask/``; non-zero = foreground, as Neural Body tests them)
and the SMPL fits ``new_params/<frame>.npy`` (else ``params/``) in EasyMocap's Rh/Th form, turned
exactly into SMPL rows (:func:`deliffas.geometry.smpl_params.rhth_to_params`). Frame f is image
``<f>`` (CoreView_313/315 name images from 1: frame = number - 1, as Neural Body). Lens distortion
``D`` is undone when frames are read. Needs the SMPL model file (``--template``).
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import numpy as np

from deliffas.io.format_registry import CaptureFormat, register_capture_format
from deliffas.io.formats.capture_frames import FileFramesSpec, image_file_size, write_image_file
from deliffas.io.formats.easymocap import EasyMocapSmpl
from deliffas.io.formats.zju_mocap import (cameras_to_zju, read_zju_annots, read_zju_params, write_zju_annots,
                                           write_zju_params, zju_params_path, zju_to_cameras)
from deliffas.data.subjects.base import Subject, SubjectOptions, SubjectSequence
from deliffas.data.subjects.export_frames import ExportFrames
from deliffas.data.subjects.capture_common import (SEQUENCE, read_test_cameras, rhth_motion, smpl_model_data,
                                                   smpl_template, split_distortion)

__all__ = ["parse_zju_mocap", "export_zju_mocap"]

ONE_BASED = ("CoreView_313", "CoreView_315")
"""Subjects whose image names start at 1 (Neural Body subtracts one)."""


def _frame_of(path: str, index: int, one_based: bool) -> int:
    stem = PurePosixPath(path.replace("\\", "/")).stem
    return int(stem) - (1 if one_based else 0) if stem.isdigit() else index


def parse_zju_mocap(root: Path, options: SubjectOptions = SubjectOptions()) -> Subject:
    """Read a ZJU-MoCap subject folder (see the module docstring)."""
    root = Path(root)
    annots = read_zju_annots(root / "annots.npy")
    if not annots.ims:
        raise ValueError(f"{root / 'annots.npy'}: ims: expected image paths per frame, got none")
    spec = smpl_template(options, "ZJU-MoCap")
    sizes = [image_file_size(root / path) for path in annots.ims[0]]  # each camera's first image
    size = sizes[0]
    cameras, undistort = split_distortion(zju_to_cameras(annots, sizes), "ZJU-MoCap")
    mask_dir = next((d for d in ("mask_cihp", "mask") if (root / d).is_dir()), None)
    params_dir = "new_params" if (root / "new_params").is_dir() else "params"
    one_based = root.name in ONE_BASED
    images, masks, frames = {}, {}, []
    for i, paths in enumerate(annots.ims):  # frames
        f = _frame_of(paths[0], i, one_based)
        if not zju_params_path(root, f, params_dir == "new_params").is_file():
            continue  # Neural Body uses only frames with SMPL parameters
        frames.append(f)
        images[f] = tuple(paths)
        if mask_dir is not None:
            masks[f] = tuple(f"{mask_dir}/{str(PurePosixPath(p).with_suffix('.png'))}" for p in paths)
    if not frames:
        raise FileNotFoundError(f"{root / params_dir}: no <frame>.npy SMPL parameters for the frames of annots.npy")
    model = smpl_model_data(spec)
    records = [read_zju_params(zju_params_path(root, f, params_dir == "new_params")) for f in frames]
    motion = rhth_motion(frames, records, model, str(root / params_dir))
    source = FileFramesSpec(root, images, masks if mask_dir else None, "nonzero", undistort)
    seq = SubjectSequence(SEQUENCE, motion.frames, int(min(frames)), size[0], size[1], source, motion)
    return Subject(root, "zju", cameras, spec, {SEQUENCE: seq}, read_test_cameras(root, options.test_cameras))


def export_zju_mocap(fr: ExportFrames, out: Path, q: int) -> None:
    """Write ``fr`` as a ZJU-MoCap folder: ``Camera_B<i>/<frame>.jpg``, 0/1 masks, ``annots.npy``, ``params/``."""
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


register_capture_format(CaptureFormat("zju", detect_subject=lambda root: (root / "annots.npy").is_file(),
                                      parse_subject=parse_zju_mocap, export=export_zju_mocap))
