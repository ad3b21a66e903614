"""AMASS-style SMPL motion files (``.npz``) read into and written from a plain record.

Layout (AMASS, https://amass.is.tue.mpg.de): ``poses`` (N, 3k) axis-angle per joint in the body
model's joint order (k = 24 for SMPL, 52 for SMPL-H, 55 for SMPL-X), ``trans`` (N, 3) metres,
``betas`` (>= 10,), optional ``mocap_framerate`` (``mocap_frame_rate`` in AMASS's SMPL-X release)
and ``gender``. Units and axes stay the file's: AMASS's world is z-up, which lives in the root
orientation and ``trans``; nothing is converted here. The SMPL-H/X layouts share SMPL's first 22
joints (root + 21 body joints, ``poses[:, :66]``) and then continue with the fingers (SMPL-H) or the
jaw and eyes (SMPL-X), so :attr:`SMPLMotion.smpl_pose` keeps those 66 values and sets SMPL's two hand
joints (``l_hand``, ``r_hand``) to zero rather than reading finger rotations as hand rotations.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float, Integer

from deliffas.io.infra.reader_checks import CaptureFormatError, read_npz
from deliffas.io.infra.files import durable_replace, temp_path

__all__ = ["SMPLMotion", "SMPLMotionError", "read_smpl_motion", "write_smpl_motion", "SMPL_POSE_DIM",
           "SMPL_BODY_POSE_DIM", "MIN_BETAS"]

SMPL_POSE_DIM = 72
"""SMPL's 24 joints x 3 axis-angle values."""
SMPL_BODY_POSE_DIM = 66
"""Root + 21 body joints: the part SMPL, SMPL-H and SMPL-X share."""
MIN_BETAS = 10
_FPS_KEYS = ("mocap_framerate", "mocap_frame_rate")


class SMPLMotionError(ValueError):
    """An AMASS-style motion file (or record) that breaks the layout; the message names file and key."""


@dataclass(frozen=True)
class SMPLMotion:
    """One SMPL(-H/-X) motion as the file holds it.

    Attributes:
        poses: (N, 3k) float64 axis-angle, radians, body-model joint order (k = 24 SMPL, 52 SMPL-H,
            55 SMPL-X), the root orientation first.
        trans: (N, 3) float64 root translation, metres, the file's world (z-up for AMASS).
        betas: (NB,) float64 shape coefficients, NB >= 10 (16 in AMASS's SMPL-H release).
        fps: capture frame rate in Hz, or None when the file gives none.
        gender: ``"male"``/``"female"``/``"neutral"`` as the file says, or None.
        frames: (N,) int64 strictly increasing capture frame number of each row (a deliffas key, e.g.
            SMPL fitted to a capture); None = rows are frames 0..N-1, as AMASS files have it.
    """

    poses: Float[np.ndarray, "N P"]
    trans: Float[np.ndarray, "N 3"]
    betas: Float[np.ndarray, "NB"]
    fps: float | None = None
    gender: str | None = None
    frames: Integer[np.ndarray, "N"] | None = None

    def __post_init__(self) -> None:
        for key in ("poses", "trans", "betas"):
            object.__setattr__(self, key, np.asarray(getattr(self, key), np.float64))
        _check_arrays("SMPLMotion", self.poses, self.trans, self.betas)
        if self.frames is not None:
            frames = np.asarray(self.frames)
            if (frames.shape != (self.poses.shape[0],) or frames.dtype.kind not in "iu"
                    or (len(frames) > 1 and np.any(np.diff(frames) <= 0))):
                raise SMPLMotionError(f"SMPLMotion: 'frames' expected {self.poses.shape[0]} strictly increasing "
                                      f"integers, got shape {frames.shape}, dtype {frames.dtype}")
            object.__setattr__(self, "frames", frames.astype(np.int64))

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    @property
    def smpl_pose(self) -> np.ndarray:
        """(N, 72) float64 SMPL pose: the file's 72 values, or for SMPL-H/X the shared first 66
        (root + 21 body joints) followed by zeros for SMPL's ``l_hand`` and ``r_hand``."""
        if self.poses.shape[1] == SMPL_POSE_DIM:
            return self.poses.copy()
        out = np.zeros((self.num_frames, SMPL_POSE_DIM))
        out[:, :SMPL_BODY_POSE_DIM] = self.poses[:, :SMPL_BODY_POSE_DIM]
        return out


def _check_arrays(where: str, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray) -> None:
    """Raise SMPLMotionError naming ``where`` and the key for a layout or value error."""
    if poses.ndim != 2 or poses.shape[1] % 3 or poses.shape[1] < SMPL_POSE_DIM:
        raise SMPLMotionError(f"{where}: 'poses' expected shape (N, 72) or (N, 3k) with k >= 24 joints, "
                              f"got {poses.shape}")
    if trans.ndim != 2 or trans.shape[1] != 3:
        raise SMPLMotionError(f"{where}: 'trans' expected shape (N, 3), got {trans.shape}")
    if trans.shape[0] != poses.shape[0]:
        raise SMPLMotionError(f"{where}: 'trans' has {trans.shape[0]} frames but 'poses' has {poses.shape[0]}")
    if betas.ndim != 1 or betas.shape[0] < MIN_BETAS:
        raise SMPLMotionError(f"{where}: 'betas' expected shape (NB,) with NB >= {MIN_BETAS}, got {betas.shape}")
    for key, a in (("poses", poses), ("trans", trans), ("betas", betas)):
        bad = int((~np.isfinite(a)).sum())
        if bad:
            raise SMPLMotionError(f"{where}: '{key}' holds {bad} NaN or inf values")


def _float_array(path: Path, z: dict, key: str) -> np.ndarray:
    a = z[key]
    if a.dtype.kind not in "fiu":
        raise SMPLMotionError(f"{path}: '{key}' expected a float array, got dtype {a.dtype}")
    return np.asarray(a, np.float64)


def _optional_text(z: dict, key: str) -> str | None:
    a = z.get(key)  # read_npz leaves a pickled entry out: not needed for posing, so not fatal
    if a is None:
        return None
    value = a.item() if a.shape == () else (a.ravel()[0] if a.size else None)
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value) if value is not None else None


def read_smpl_motion(path: str | os.PathLike) -> SMPLMotion:
    """Read an AMASS-style ``.npz`` (never unpickling) and check its layout.

    Raises:
        FileNotFoundError: the file does not exist.
        SMPLMotionError: a damaged archive, a missing key, a wrong shape, a pose length that is not 72 or 3k
            (k >= 24), no frames, a different frame count in ``poses`` and ``trans``, NaN/inf values, or a bad
            frame rate; the message names the file and the key.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"SMPL motion file not found: {p}")
    try:
        z = read_npz(p, text_keys=("gender",))
    except CaptureFormatError as err:
        raise SMPLMotionError(f"{p}: '{err.key}' {err.expectation}") from None
    missing = [k for k in ("poses", "trans", "betas") if k not in z]
    if missing:
        raise SMPLMotionError(f"{p}: missing keys {missing} (has {sorted(z)})")
    poses, trans, betas = (_float_array(p, z, k) for k in ("poses", "trans", "betas"))
    _check_arrays(str(p), poses, trans, betas.ravel() if betas.ndim == 2 and betas.shape[0] == 1 else betas)
    if poses.shape[0] == 0:
        raise SMPLMotionError(f"{p}: 'poses' expected at least one frame, got none")
    fps = None
    for key in _FPS_KEYS:
        if key in z:
            value = _float_array(p, z, key)
            if value.size != 1 or not np.isfinite(value).all() or float(value.ravel()[0]) <= 0:
                raise SMPLMotionError(f"{p}: '{key}' expected one positive frame rate, got shape {value.shape}")
            fps = float(value.ravel()[0])
            break
    gender = _optional_text(z, "gender")
    frames = z.get("frames")
    if frames is not None and (frames.dtype.kind not in "iu" or frames.shape != (poses.shape[0],)):
        raise SMPLMotionError(f"{p}: 'frames' expected {poses.shape[0]} integer frame numbers (one per row of 'poses'), "
                              f"got shape {frames.shape}, dtype {frames.dtype}")
    try:
        return SMPLMotion(poses, trans, betas.ravel(), fps, gender, frames)
    except SMPLMotionError as err:
        raise SMPLMotionError(f"{p}: {str(err).split(': ', 1)[1]}") from None


def write_smpl_motion(path: str | os.PathLike, motion: SMPLMotion) -> None:
    """Write ``motion`` as an AMASS-style ``.npz`` (``poses``, ``trans``, ``betas``, ``mocap_framerate``
    when known, ``gender`` when known) under a temporary name, then rename it into place."""
    p = Path(path)
    if p.suffix.lower() != ".npz":
        raise SMPLMotionError(f"{p}: write_smpl_motion writes .npz files, got '{p.suffix}'")
    arrays = {"poses": np.asarray(motion.poses, np.float64), "trans": np.asarray(motion.trans, np.float64),
              "betas": np.asarray(motion.betas, np.float64)}
    if motion.fps is not None:
        arrays["mocap_framerate"] = np.asarray(float(motion.fps))
    if motion.gender is not None:
        arrays["gender"] = np.asarray(str(motion.gender))
    if motion.frames is not None:
        arrays["frames"] = np.asarray(motion.frames, np.int64)
    tmp = temp_path(p)
    with open(tmp, "wb") as fh:  # a file object: np.savez would append .npz to the temporary name
        np.savez(fh, **arrays)
    durable_replace(tmp, p)
