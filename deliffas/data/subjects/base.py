"""The ``Subject`` record every capture format is parsed into, and ``parse_subject`` over the format registry.

A parser (one module per capture format, nerfstudio's DataParser idea with typed records) turns a
capture folder into a :class:`Subject`: cameras in the deliffas convention (mm, world -> camera,
pixel centres at +0.5), per sequence the frames it has, where its images and masks are, and the
template's per-frame pose parameters, plus the template spec and the train/test camera split.
Pixels are not loaded here: :meth:`FrameSourceSpec.open` opens them in the process that reads.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Mapping

import numpy as np
from jaxtyping import Integer

from deliffas.io.cameras import Camera
from deliffas.io.format_registry import capture_format, capture_formats
from deliffas.io.motion import Motion
from deliffas.io.formats.dynacap.frames import FrameSource, FramesSpec, ImageFolderSource, open_frame_source
from deliffas.geometry.templates import TemplateSpec
from deliffas.data.subject_options import SubjectOptions

__all__ = [
    "FrameSourceSpec",
    "SubjectSequence",
    "Subject",
    "SubjectOptions",
    "subject_format_names",
    "parse_subject",
]


@dataclass(frozen=True)
class FrameSourceSpec:
    """Where one sequence's images and masks are; picklable, opened where the pixels are read.

    Attributes:
        folder: the sequence folder.
        camera_names: calibration names by calibration index (video file names use them).
        layout: ``images`` or ``videos``.
        first_frame: capture frame of video frame 0.
        mask_dir: a mask folder replacing the images' alpha / the ``fg`` videos, or None.
    """

    folder: Path
    camera_names: tuple[str, ...]
    layout: Literal["images", "videos"]
    first_frame: int = 0
    mask_dir: Path | None = None

    def open(self) -> FrameSource:
        return open_frame_source(self.folder, self.camera_names, self.layout, self.first_frame, self.mask_dir)

    def image_frames(self) -> set[int] | None:
        """Frame numbers that have images (None: a video layout, where every frame of the video has one)."""
        return set(ImageFolderSource(self.folder).frames()) if self.layout == "images" else None


@dataclass(frozen=True)
class SubjectSequence:
    """One captured sequence (e.g. ``training``, ``testing``).

    Attributes:
        name: sequence name; shards and splits refer to it.
        frames: (N,) int64 sorted frame numbers (capture frame numbers, not rows) that have a surface
            (pose parameters or a tracked mesh).
        first_frame: the sequence's first frame number (temporal windows clamp to it).
        width: image width in pixels.
        height: image height in pixels.
        images: where its images and masks are (a ``FrameSourceSpec`` or a format's own spec).
        poses: per-frame template pose parameters (``frames`` (M,) int64 frame numbers, ``dofs``
            (M, D) float64 in the template's units: DOF units for ``ddc``, [transl m, axis-angle rad,
            betas] for ``smpl``), or None.
        surfaces: a tracked ``.meshes`` file giving the surface per frame (mm, template vertex
            order) instead of the posed template, or None.
    """

    name: str
    frames: Integer[np.ndarray, "N"]
    first_frame: int
    width: int
    height: int
    images: FramesSpec
    poses: Motion | None = None
    surfaces: Path | None = None


@dataclass(frozen=True)
class Subject:
    """A capture parsed into deliffas conventions (docs/data.md states each format's).

    Attributes:
        root: the capture folder.
        format: the registered format that parsed it.
        cameras: every calibrated camera in calibration order, deliffas convention (world mm,
            world -> camera, pixel centres at +0.5; :class:`~deliffas.io.cameras.Camera`).
        template: the template the pose parameters drive (its spec; ``build_template`` builds it).
        sequences: name -> sequence, in the order they are converted.
        test_cameras: calibration indices held out for evaluation (sorted).
    """

    root: Path
    format: str
    cameras: tuple[Camera, ...]
    template: TemplateSpec
    sequences: Mapping[str, SubjectSequence]
    test_cameras: tuple[int, ...] = ()

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)


def subject_format_names() -> tuple[str, ...]:
    """The capture formats ``parse_subject`` reads (a ``CaptureFormat`` with ``parse_subject``), in registration order."""
    return tuple(f.name for f in capture_formats("parse_subject"))


def parse_subject(path: str | os.PathLike, format: str = "auto", options: SubjectOptions = SubjectOptions()) -> Subject:
    """Read a capture folder into a :class:`Subject`.

    Args:
        path: the capture folder.
        format: a registered format name, or ``auto`` (the first whose ``detect`` accepts the folder).

    Raises:
        FileNotFoundError: the folder does not exist.
        ValueError: unknown format, or no format recognises the folder (the message lists them).
    """
    root = Path(path).resolve()
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: capture folder not found")
    if format == "auto":
        formats = capture_formats("detect_subject", "parse_subject")
        for f in formats:
            if f.detect_subject(root):
                return f.parse_subject(root, options)
        names = ", ".join(f.name for f in formats)
        raise ValueError(f"{root}: not a capture of any known format ({names}); pass --format")
    return capture_format(format, "parse_subject").parse_subject(root, options)
