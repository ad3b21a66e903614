"""Writing one sequence of an SMPL ``Subject`` (e.g. a synthetic capture) in a capture dataset's own layout.

``export_capture(subject, out, fmt)`` writes the cameras, frames and SMPL parameters through the
exporter ``fmt`` registered (``CaptureFormat.export``, in the format's module under
``deliffas/data/subjects/``; ``export_format_names()`` lists them), with JPEG where the dataset stores
JPEG. It exists so that each parser is tested on files written by another code path; SMPL parameters
are written in each dataset's own form (Rh/Th, SMPL-X, AMASS). The SMPL model file is not copied (the
datasets do not hold it; the parser takes it as ``--template``).
"""

from __future__ import annotations

import os
from pathlib import Path

from deliffas.io.format_registry import capture_format, capture_formats
from deliffas.data.subjects import Subject
from deliffas.data.subjects.export_frames import ExportFrames

__all__ = ["export_format_names", "export_capture"]


def export_format_names() -> tuple[str, ...]:
    """Layouts ``export_capture`` writes (the parser of the same format reads them)."""
    return tuple(f.name for f in capture_formats("export"))


def export_capture(subject: Subject, out_dir: str | os.PathLike, fmt: str, sequence: str = "training",
                   jpeg_quality: int = 95) -> Path:
    """Write ``sequence`` of an SMPL ``subject`` as a ``fmt`` capture folder; returns the folder.

    Raises:
        ValueError: an unknown format (or one without an exporter), a non-SMPL subject, or frames the layout
            cannot number.
        FileExistsError: ``out_dir`` exists and is not empty.
    """
    export = capture_format(fmt, "export").export
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out}: not empty; export writes a new capture folder")
    frames = ExportFrames(subject, sequence)
    out.mkdir(parents=True, exist_ok=True)
    export(frames, out, int(jpeg_quality))
    return out
