"""THuman4.0 / AvatarReX ``calibration.json`` cameras and ``smpl_params.npz`` SMPL-X fits as plain records.

Conventions, worked out from the dataset pages and the Animatable Gaussians loader
(lizhe00/AnimatableGaussians @2b0f6e3: ``dataset/dataset_mv_rgb.py``, ``AVATARREX_DATASET.md``;
ZhengZerong/THUman4.0-Dataset @0cfc834: ``Readme.md``):

- ``calibration.json`` (THuman4.0; AvatarReX ships ``calibration_full.json`` in the same layout) is an
  object keyed by camera name (``cam00``, ... for THuman4.0; serial numbers for AvatarReX), each with
  ``K`` (3 x 3, read with ``reshape(3, 3)``: nested or flat, row-major), ``R`` (3 x 3), ``T`` (3) and
  ``imgSize`` [width, height] (``img_widths = imgSize[0]``).
- Pose: world -> camera; the Readme projects SMPL-X vertices with ``verts @ R^T + T`` then ``K``.
- Units: **metres** (SMPL-X vertices, in metres, are projected with T as it is); deliffas x 1000.
- Pixels: the loader samples pixel (x, y) at the integer point (``utils/nerf_util.py::gen_uv``,
  ``np.linspace(0, w - 1, w)``) and the Readme rounds projections to the nearest integer index:
  OpenCV pixel centres, cx_deliffas = cx + 0.5.
- Distortion: no public reader reads any (Animatable Gaussians builds K, R, T only), so the images are
  taken as undistorted. A camera entry with a ``distCoeff`` or ``D`` list is kept (OpenCV order) in
  ``Camera.extra["distortion"]``; the writer refuses non-zero distortion (``LossyConversionError``)
  unless told to drop it, since no reader of this format would apply it.
- Images ``images/<cam>/<frame:08d>.jpg`` and masks ``masks/<cam>/<frame:08d>.jpg`` (THuman4.0;
  AvatarReX: ``<cam>/<frame:08d>.jpg`` and ``<cam>/mask/pha/<frame:08d>.jpg``), frames 0-based.
- ``smpl_params.npz``: per frame ``global_orient`` (N, 3), ``transl`` (N, 3) metres, ``body_pose``
  (N, 63), ``jaw_pose``, ``expression``, ``left_hand_pose``/``right_hand_pose`` (N, 45, no PCA), and
  ``betas`` (1, 10) shared; the Readme indexes frame ``f`` as row ``f``. Read as a record; no SMPL maths.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.camera_conventions import from_camera, require_distortion_fits, to_camera
from deliffas.io.infra.reader_checks import (CaptureFormatError, read_json, read_npz, require_array, require_rotation,
                                        require_rows, require_size, require_vector, write_json_atomic)
from deliffas.io.infra.files import durable_replace, temp_path
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.formats.camera_files import converted, file_detector

__all__ = [
    "Thuman4Camera",
    "Thuman4Smplx",
    "read_thuman4_calibration",
    "thuman4_calibration_path",
    "write_thuman4_calibration",
    "thuman4_to_camera",
    "camera_to_thuman4",
    "read_thuman4_smplx",
    "write_thuman4_smplx",
    "thuman4_image_path",
    "thuman4_mask_path",
]

PathLike = str | os.PathLike

_DISTORTION_KEYS = ("distCoeff", "D")
_SMPLX_REQUIRED = ("betas", "global_orient", "transl", "body_pose")
_SMPLX_OPTIONAL = ("jaw_pose", "expression", "left_hand_pose", "right_hand_pose")


@dataclass(frozen=True)
class Thuman4Camera:
    """One camera of ``calibration.json``, in the file's conventions.

    Attributes:
        name: the JSON key (``cam00``).
        K: (3, 3) float64 intrinsics, pixels, OpenCV pixel centres.
        R: (3, 3) float64 world -> camera rotation.
        T: (3,) float64 world -> camera translation, metres.
        width: ``imgSize[0]``, pixels.
        height: ``imgSize[1]``, pixels.
        distortion: (5,) float64 OpenCV distortion from a ``distCoeff``/``D`` entry, or None (the usual case).
    """

    name: str
    K: np.ndarray
    R: np.ndarray
    T: np.ndarray
    width: int
    height: int
    distortion: np.ndarray | None = None


@dataclass(frozen=True)
class Thuman4Smplx:
    """``smpl_params.npz``: SMPL-X parameters per frame (no SMPL maths here).

    Attributes:
        betas: (1, B) float64 shape, shared by all frames.
        global_orient: (N, 3) float64 axis-angle radians.
        transl: (N, 3) float64 metres.
        body_pose: (N, 63) float64 axis-angle radians (21 joints).
        others: the optional arrays (``jaw_pose`` (N, 3), ``expression`` (N, E), ``left_hand_pose``/
            ``right_hand_pose`` (N, 45)) present in the file, each (N, ...) float64.
    """

    betas: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    body_pose: np.ndarray
    others: dict

    @property
    def num_frames(self) -> int:
        return int(self.global_orient.shape[0])


def thuman4_calibration_path(path: PathLike) -> Path:
    """The calibration file ``path`` names: itself, or in a folder ``calibration.json`` (else ``calibration_full.json``)."""
    p = Path(path)
    if p.is_dir():
        return p / "calibration.json" if (p / "calibration.json").is_file() else p / "calibration_full.json"
    return p


def read_thuman4_calibration(path: PathLike) -> list[Thuman4Camera]:
    """Read ``calibration.json`` (or ``calibration_full.json``; a folder: whichever it holds), in file order.

    Raises:
        CaptureFormatError: naming ``<cam>.<K|R|T|imgSize>`` for a missing key, wrong shape, NaN/inf,
            non-rotation or bad size, and the JSON line for a truncated file.
    """
    p = thuman4_calibration_path(path)
    data = read_json(p)
    if not isinstance(data, dict) or not data:
        raise CaptureFormatError(p, "(top level)", "expected an object of cameras keyed by name")
    out = []
    for name, entry in data.items():
        if not isinstance(entry, dict):
            raise CaptureFormatError(p, name, "expected an object with K, R, T, imgSize")
        for key in ("K", "R", "T", "imgSize"):
            if key not in entry:
                raise CaptureFormatError(p, f"{name}.{key}", "missing")
        K = require_array(p, f"{name}.K", entry["K"], (3, 3), reshape=True)
        R = require_rotation(p, f"{name}.R", entry["R"])
        T = require_array(p, f"{name}.T", entry["T"], (3,), reshape=True)
        size = entry["imgSize"]
        if not isinstance(size, (list, tuple)) or len(size) != 2:
            raise CaptureFormatError(p, f"{name}.imgSize", f"expected [width, height], got {size!r}"[:120])
        w, h = require_size(p, f"{name}.imgSize", *size)
        dist = None
        for key in _DISTORTION_KEYS:
            if key in entry:
                d = require_vector(p, f"{name}.{key}", entry[key])
                if d.size not in (4, 5):
                    raise CaptureFormatError(p, f"{name}.{key}", f"expected 4 or 5 OpenCV coefficients, got {d.size}")
                dist = np.zeros(5)
                dist[: d.size] = d
        out.append(Thuman4Camera(str(name), K, R, T, w, h, dist))
    return out


def write_thuman4_calibration(path: PathLike, cameras: Sequence[Thuman4Camera]) -> Path:
    """Write ``calibration.json`` (``path`` a file, or a folder to hold it), full precision, atomically.

    ``K`` and ``R`` are written as nested 3 x 3 lists; ``distCoeff`` only for a camera with non-zero distortion.
    """
    p = Path(path)
    if p.is_dir() or p.suffix != ".json":
        p = p / "calibration.json"
    data = {}
    for c in cameras:
        entry = {"K": np.asarray(c.K, np.float64).tolist(), "R": np.asarray(c.R, np.float64).tolist(),
                 "T": np.asarray(c.T, np.float64).tolist(), "imgSize": [int(c.width), int(c.height)]}
        if c.distortion is not None and np.any(np.asarray(c.distortion) != 0):
            entry["distCoeff"] = np.asarray(c.distortion, np.float64).tolist()
        if c.name in data:
            raise ValueError(f"THuman4 calibration: camera name {c.name!r} appears twice")
        data[c.name] = entry
    write_json_atomic(p, data)
    return p


def thuman4_to_camera(cam: Thuman4Camera) -> Camera:
    """The deliffas Camera (mm, +0.5 pixel centres, distortion in ``extra`` when the file has it)."""
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = cam.R, cam.T
    return to_camera(cam.name, cam.K, E, cam.width, cam.height, units="m", pixel_centre="integer",
                     distortion=cam.distortion)


def camera_to_thuman4(camera: Camera, drop_distortion: bool = False) -> Thuman4Camera:
    """The ``calibration.json`` record of a deliffas Camera (metres, OpenCV pixel centres).

    Raises:
        LossyConversionError: the camera has lens distortion (no THuman4.0 reader applies any).
    """
    camera = require_distortion_fits(camera, "THuman4.0 calibration.json", (), drop_distortion)
    K, E, _ = from_camera(camera, units="m", pixel_centre="integer")
    return Thuman4Camera(camera.name, K, E[:3, :3].copy(), E[:3, 3].copy(), camera.width, camera.height)


def read_thuman4_smplx(path: PathLike) -> Thuman4Smplx:
    """Read ``smpl_params.npz`` (arrays only; a pickled entry is refused).

    Raises:
        CaptureFormatError: missing/truncated file, a missing key, inconsistent frame counts, NaN/inf.
    """
    p = Path(path)
    arrays = read_npz(p)
    for key in _SMPLX_REQUIRED:
        if key not in arrays:
            raise CaptureFormatError(p, key, "missing")
    go = require_array(p, "global_orient", arrays["global_orient"], (-1, 3))
    n = go.shape[0]
    if n == 0:
        raise CaptureFormatError(p, "global_orient", "expected at least one frame, got none")
    transl = require_array(p, "transl", arrays["transl"], (n, 3))
    bp = arrays["body_pose"]
    if bp.shape == (n, 21, 3):  # (N, 21, 3) is stored too
        bp = bp.reshape(n, 63)
    body = require_array(p, "body_pose", bp, (n, 63))
    betas = require_rows(p, "betas", arrays["betas"])
    others = {}
    for key in _SMPLX_OPTIONAL:
        if key in arrays:
            a = arrays[key]
            others[key] = require_array(p, key, a, (n,) + (-1,) * (a.ndim - 1))
    return Thuman4Smplx(betas, go, transl, body, others)


def write_thuman4_smplx(path: PathLike, smplx: Thuman4Smplx) -> None:
    """Write ``smpl_params.npz`` (float64 arrays, the optional ones from ``others``), atomically."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: np.asarray(getattr(smplx, k), np.float64) for k in _SMPLX_REQUIRED}
    arrays.update({k: np.asarray(v, np.float64) for k, v in smplx.others.items()})
    tmp = temp_path(p)
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    durable_replace(tmp, p)


def thuman4_image_path(root: PathLike, camera: str, frame: int) -> Path:
    """``root/images/<camera>/<frame:08d>.jpg`` (THuman4.0 layout)."""
    return Path(root) / "images" / camera / f"{int(frame):08d}.jpg"


def thuman4_mask_path(root: PathLike, camera: str, frame: int) -> Path:
    """``root/masks/<camera>/<frame:08d>.jpg`` (THuman4.0 layout)."""
    return Path(root) / "masks" / camera / f"{int(frame):08d}.jpg"


# ----------------------------------------------------------------------------------- capture format
def _is_calibration(path: Path) -> bool:
    """A JSON object of camera name -> object (and not nerfstudio's ``frames``)."""
    data = read_json(path)
    return isinstance(data, dict) and "frames" not in data and all(isinstance(v, dict) for v in data.values())


FORMAT = CaptureFormat(
    "thuman4", "THuman4.0 / AvatarReX calibration.json", camera_path="calibration.json", distortion=(),
    stores_size=True,
    detect_cameras=file_detector("calibration.json", "calibration_full.json", suffixes=(".json",),
                                 accept=_is_calibration),
    read_cameras=lambda path, size: converted(thuman4_calibration_path(path), read_thuman4_calibration(path),
                                              thuman4_to_camera),
    write_cameras=lambda cameras, out, options: write_thuman4_calibration(
        out, [camera_to_thuman4(c, options.drop_distortion) for c in cameras]))
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
