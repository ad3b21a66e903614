"""The ``dna`` capture format: a DNA-Rendering ``.smc`` capture (main file + optional ``_annots.smc``) as a Subject.

The folder holds ``<name>.smc`` (JPEG colour frames, ``Camera_5mp``; or ``extra["smc_group"]``) and
optionally ``<name>_annots.smc`` (calibration, masks, SMPL-X); every group is taken from whichever file
has it. Cameras: metres, ``RT`` camera -> world, OpenCV pixel centres and distortion (undone when
frames are read). SMPL-X ``fullpose`` (N, 55, 3) -> SMPL: global orientation and the 21 body joints
are copied with ``transl``, SMPL's hand joints zero; jaw, eyes, fingers and expression are dropped, and
the first 10 betas are used in the SMPL model's shape space (exact only for a capture fitted with that
SMPL model). A ``scale`` other than 1 is refused. Needs the SMPL model file (``--template``).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from deliffas.io.format_registry import CaptureFormat, register_capture_format
from deliffas.io.formats.capture_frames import SmcFramesSpec
from deliffas.io.formats.dna_rendering import SmcFile, SmcSmplx, cameras_to_smc, smc_to_cameras, write_smc
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.motion import Motion
from deliffas.geometry.smpl_params import smplx_to_smpl_pose
from deliffas.data.subjects.base import Subject, SubjectOptions, SubjectSequence
from deliffas.data.subjects.export_frames import ExportFrames
from deliffas.data.subjects.capture_common import SEQUENCE, fit_betas, read_test_cameras, smpl_template, split_distortion

__all__ = ["parse_dna_rendering", "export_dna_rendering"]


def _files(root: Path) -> tuple[Path, Path | None]:
    mains = sorted(p for p in root.glob("*.smc") if not p.stem.endswith("_annots"))
    if len(mains) != 1:
        raise FileNotFoundError(f"{root}: expected one <name>.smc (besides <name>_annots.smc), found "
                                f"{[p.name for p in mains]}")
    annots = mains[0].with_name(f"{mains[0].stem}_annots.smc")
    return mains[0], annots if annots.is_file() else None


def parse_dna_rendering(root: Path, options: SubjectOptions = SubjectOptions()) -> Subject:
    """Read a DNA-Rendering capture folder (see the module docstring)."""
    root = Path(root)
    main_path, annots_path = _files(root)
    group = str(options.extra.get("smc_group", "Camera_5mp"))
    with contextlib.ExitStack() as stack:  # each file opened once: every open checks the whole file's heaps
        main = stack.enter_context(SmcFile(main_path))
        annots = stack.enter_context(SmcFile(annots_path)) if annots_path is not None else None
        pick = {g: annots if annots is not None and annots.has(g) else main for g in ("Camera_Parameter", "Mask", "SMPLx")}
        calib = smc_to_cameras(pick["Camera_Parameter"], group=group, images=main)
        cameras, undistort = split_distortion(calib, "DNA-Rendering")
        spec = smpl_template(options, "DNA-Rendering")
        ids = tuple(str(int(c.camera_id)) for c in pick["Camera_Parameter"].calibration())
        stored = min(main.frame_count(cid, group) for cid in ids)
        smplx = pick["SMPLx"].smplx()
        smplx_path, mask_path = pick["SMPLx"].path, (pick["Mask"].path if pick["Mask"] is not main else None)
    if abs(smplx.scale - 1.0) > 1e-9:
        raise CaptureFormatError(smplx_path, "SMPLx/scale", f"expected 1 (a scaled SMPL-X fit is not supported), "
                                                            f"got {smplx.scale:g}")
    n = min(stored, len(smplx.fullpose))
    if n == 0:
        raise CaptureFormatError(main_path, group, "expected frames with SMPL-X parameters, got none")
    rows = np.arange(n)
    betas = fit_betas(smplx.betas[0], f"{smplx_path}: SMPLx/betas")
    pose = smplx_to_smpl_pose(smplx.fullpose[:n, 0], smplx.fullpose[:n, 1:22].reshape(n, -1))
    motion = Motion(rows.astype(np.int64), np.concatenate([smplx.transl[:n], pose, np.tile(betas, (n, 1))], axis=1))
    source = SmcFramesSpec(main_path, ids, tuple(int(f) for f in rows), group, mask_path, undistort)
    seq = SubjectSequence(SEQUENCE, motion.frames, 0, cameras[0].width, cameras[0].height, source, motion)
    return Subject(root, "dna", cameras, spec, {SEQUENCE: seq}, read_test_cameras(root, options.test_cameras))


def export_dna_rendering(fr: ExportFrames, out: Path, q: int) -> None:
    """Write ``fr`` as one DNA-Rendering ``<out name>.smc`` (calibration, JPEG images and masks, SMPL-X)."""
    fr.require_frames_from_zero("dna", ".smc")
    calib = cameras_to_smc(fr.cameras)
    images = {c.camera_id: [] for c in calib}
    masks = {c.camera_id: [] for c in calib}
    for _, c, rgb, mask in fr.pixels():
        images[calib[c].camera_id].append(rgb)
        masks[calib[c].camera_id].append(mask)
    smplx = SmcSmplx(fr.betas[None], np.zeros((len(fr.frames), 10)), fr.smplx_pose(), fr.params[:, :3].copy())
    write_smc(out / f"{out.name}.smc", calib, images, masks, smplx, jpeg_quality=q)


register_capture_format(CaptureFormat("dna", detect_subject=lambda root: any(root.glob("*.smc")),
                                      parse_subject=parse_dna_rendering, export=export_dna_rendering))
