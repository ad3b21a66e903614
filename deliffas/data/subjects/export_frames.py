"""One sequence of an SMPL ``Subject`` as a format's exporter needs it: frames, SMPL rows, pixels, EasyMocap/SMPL-X forms.

A format that can be exported registers ``CaptureFormat.export = fn(frames: ExportFrames, out, jpeg_quality)``
in its module under ``deliffas/data/subjects/``; ``deliffas.data.export_capture`` builds the
:class:`ExportFrames` and calls it.
"""

from __future__ import annotations

import numpy as np

from deliffas.io.body_models.amass import SMPL_BODY_POSE_DIM
from deliffas.io.body_models.smpl import load_smpl_model
from deliffas.geometry.smpl_params import params_to_rhth, rest_root_joint
from deliffas.geometry.templates import template_kind
from deliffas.data.subjects.base import Subject

__all__ = ["ExportFrames"]


class ExportFrames:
    """The sequence's frames, SMPL rows (N, 3 + 72 + NB) and pixels, as the writers need them."""

    def __init__(self, subject: Subject, sequence: str):
        if not template_kind(subject.template.kind).smpl_params:
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

    def require_frames_from_zero(self, fmt: str, what: str) -> None:
        """Raise unless the frames are 0..N-1 (``what``: the file whose rows are numbered so)."""
        if self.frames != list(range(len(self.frames))):
            raise ValueError(f"export {fmt}: {what} rows are frames 0..N-1, the sequence has {self.frames[:5]}...")

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
