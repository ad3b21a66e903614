"""The ``easymocap`` capture format: an EasyMocap dataset folder with its SMPL output as a Subject.

Reads ``intri.yml`` + ``extri.yml`` (metres, world -> camera, OpenCV pixel centres and distortion),
images ``images/<cam>/<frame:06d>.jpg`` (or .png), masks ``mask/<cam>/<frame:06d>.png|jpg`` when
present (grey values kept), and the SMPL fits ``output*/smpl/<frame:06d>.json`` (the first
``output*`` folder in name order, or ``extra["smpl_dir"]``; person ``extra["person"]``, default the
first in the file) in the Rh/Th form, turned exactly into SMPL rows. SMPL-H/X fits keep their 22 body
joints (hands, jaw, eyes, expression dropped). Frames are those with images in every camera and an
SMPL file. Needs the SMPL model file (``--template``).
"""

from __future__ import annotations

from pathlib import Path

from deliffas.io.format_registry import CaptureFormat, register_capture_format
from deliffas.io.formats.capture_frames import FileFramesSpec, image_file_size, numbered_files, write_image_file
from deliffas.io.formats.easymocap import (EasyMocapSmpl, camera_to_easymocap, easymocap_to_camera, read_easymocap_cameras,
                                           read_easymocap_smpl, write_easymocap_cameras, write_easymocap_smpl)
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.data.subjects.base import Subject, SubjectOptions, SubjectSequence
from deliffas.data.subjects.export_frames import ExportFrames
from deliffas.data.subjects.capture_common import (SEQUENCE, read_test_cameras, rhth_motion, smpl_model_data,
                                                   smpl_template, split_distortion)

__all__ = ["parse_easymocap", "export_easymocap"]


def _smpl_dir(root: Path, options: SubjectOptions) -> Path:
    if options.extra.get("smpl_dir"):
        return Path(str(options.extra["smpl_dir"]))
    found = sorted(d / "smpl" for d in root.glob("output*") if (d / "smpl").is_dir())
    if not found:
        raise FileNotFoundError(f"{root}: no output*/smpl/ folder of SMPL fits (EasyMocap's mv1p output)")
    return found[0]


def _person(path: Path, person):
    people = read_easymocap_smpl(path)
    if not people:
        raise CaptureFormatError(path, "(top level)", "expected at least one person, got an empty list")
    if person is None:
        return people[0]
    for p in people:
        if p.id == int(person):
            return p
    raise CaptureFormatError(path, "id", f"expected person {person}, found ids {[p.id for p in people]}")


def parse_easymocap(root: Path, options: SubjectOptions = SubjectOptions()) -> Subject:
    """Read an EasyMocap dataset folder (see the module docstring)."""
    root = Path(root)
    records = read_easymocap_cameras(root / "intri.yml", root / "extri.yml")
    names = [c.name for c in records]
    spec = smpl_template(options, "EasyMocap")
    per_cam = [numbered_files(root / "images" / n) for n in names]
    smpl_files = numbered_files(_smpl_dir(root, options), suffixes=(".json",))
    frames = sorted(set(smpl_files).intersection(*map(set, per_cam)))
    if not frames:
        raise FileNotFoundError(f"{root}: no frame has an image in every camera (images/<cam>/<frame:06d>.jpg) "
                                f"and an SMPL file ({len(smpl_files)} SMPL files)")
    size = image_file_size(per_cam[0][frames[0]])
    cameras, undistort = split_distortion(  # no W_/H_ in intri.yml: the camera's first image
        [easymocap_to_camera(c, None if c.width and c.height else image_file_size(per_cam[i][frames[0]]))
         for i, c in enumerate(records)], "EasyMocap")
    mask_cam = [numbered_files(root / "mask" / n) for n in names]
    have_masks = all(f in m for m in mask_cam for f in frames)
    images = {f: tuple(str(per_cam[c][f].relative_to(root)) for c in range(len(names))) for f in frames}
    masks = ({f: tuple(str(mask_cam[c][f].relative_to(root)) for c in range(len(names))) for f in frames}
             if have_masks else None)
    people = [_person(smpl_files[f], options.extra.get("person")) for f in frames]
    motion = rhth_motion(frames, people, smpl_model_data(spec), str(smpl_files[frames[0]].parent))
    source = FileFramesSpec(root, images, masks, "gray", undistort)
    seq = SubjectSequence(SEQUENCE, motion.frames, frames[0], size[0], size[1], source, motion)
    return Subject(root, "easymocap", cameras, spec, {SEQUENCE: seq}, read_test_cameras(root, options.test_cameras))


def _is_easymocap(root: Path) -> bool:
    return (root / "intri.yml").is_file() and (root / "extri.yml").is_file()


def export_easymocap(fr: ExportFrames, out: Path, q: int) -> None:
    """Write ``fr`` as an EasyMocap folder: cameras, ``images/``, ``mask/``, ``output/smpl/<frame>.json``."""
    write_easymocap_cameras(out, [camera_to_easymocap(c) for c in fr.cameras])
    for f, c, rgb, mask in fr.pixels():
        write_image_file(out / "images" / fr.cameras[c].name / f"{f:06d}.jpg", rgb, q)
        write_image_file(out / "mask" / fr.cameras[c].name / f"{f:06d}.png", mask)
    Rh, Th, poses = fr.rhth()
    for i, f in enumerate(fr.frames):
        write_easymocap_smpl(out / "output" / "smpl" / f"{f:06d}.json",
                             [EasyMocapSmpl(0, Rh[i:i + 1], Th[i:i + 1], poses[i:i + 1], fr.betas[None])])


register_capture_format(CaptureFormat("easymocap", detect_subject=_is_easymocap, parse_subject=parse_easymocap,
                                      export=export_easymocap))
