"""nerfstudio ``transforms.json`` cameras (one frame per camera) as plain records.

Conventions, worked out from nerfstudio (nerfstudio-project/nerfstudio @50e0e3c):

- Layout (``nerfstudio/data/dataparsers/nerfstudio_dataparser.py``): top-level ``frames``, each with
  ``file_path`` and ``transform_matrix`` (4 x 4); intrinsics ``fl_x, fl_y, cx, cy, w, h`` and
  distortion ``k1, k2, k3, k4, p1, p2`` either per frame or once at the top level (a per-frame value
  wins); ``camera_model`` (``OPENCV`` for the pinhole + radial-tangential model; ``PINHOLE`` and
  ``SIMPLE_PINHOLE`` are read the same way; ``OPENCV_FISHEYE``, ``EQUIRECTANGULAR`` and the other models
  are refused: deliffas' cameras are pinholes and their k1..k4 mean something else).
- Pose: ``transform_matrix`` is **camera-to-world** with **OpenGL camera axes** (x right, y up,
  looking along -z): ``process_data/colmap_utils.py::colmap_to_json`` builds it as the inverse of
  COLMAP's world-to-camera followed by ``c2w[0:3, 1:3] *= -1``. deliffas: c2w_opencv =
  c2w_gl @ diag(1, -1, -1, 1), then ``invert_rigid``.
- World: whatever the file's world is; ``applied_transform`` (3 x 4) records how it was derived from
  the original data. deliffas writes the deliffas world unchanged with ``applied_transform`` = [I | 0]
  (nerfstudio otherwise assumes COLMAP's axis swap for files without it) and reads files ignoring it.
- Units: nerfstudio is scale-free (it rescales poses itself); deliffas reads and writes **metres**,
  so the scenes have the metric size nerfstudio's default near/far planes expect.
- Pixels: rays go through pixel (i, j) at (j + 0.5, i + 0.5) (``cameras/cameras.py::get_image_coords``,
  ``pixel_offset=0.5``) and COLMAP's cx is copied unchanged: the deliffas convention, K unchanged.
- Distortion: OpenCV's k1, k2, k3, p1, p2 (``camera_utils.radial_and_tangential_undistort``);
  k4 (an r^8 term) has no place in the deliffas 5-vector, and a non-zero k4 is refused on reading.
- Camera names: the stem of ``file_path`` (``images/cam03.png`` -> ``cam03``), unique in a file; the
  writer uses ``images/<name>.png`` unless given file paths.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Sequence, no_type_check

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.camera_conventions import OPENGL_FROM_OPENCV, from_camera, invert_rigid, require_distortion_fits, to_camera
from deliffas.io.infra.reader_checks import (CaptureFormatError, read_json, require_array, require_rotation, require_size,
                                        require_unique_names, write_json_atomic)
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.formats.camera_files import converted, file_detector, in_folder

__all__ = [
    "NerfstudioFrame",
    "read_transforms",
    "write_transforms",
    "nerfstudio_to_camera",
    "camera_to_nerfstudio",
]

PathLike = str | os.PathLike

_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DIST = ("k1", "k2", "k3", "k4", "p1", "p2")
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
"""The ``camera_model`` values deliffas reads: nerfstudio's perspective camera with OpenCV's radial-tangential
distortion (its default when the key is absent). Fisheye, equirectangular and other models are refused."""


@dataclass(frozen=True)
class NerfstudioFrame:
    """One frame of ``transforms.json`` with its intrinsics resolved (frame value, else top level).

    Attributes:
        file_path: the frame's ``file_path`` as written.
        transform_matrix: (4, 4) float64 camera -> world, OpenGL camera axes, metres.
        fl_x, fl_y, cx, cy: intrinsics in pixels, pixel centres at +0.5.
        w, h: image size in pixels.
        distortion: (6,) float64 (k1, k2, k3, k4, p1, p2), zeros where absent.
    """

    file_path: str
    transform_matrix: np.ndarray
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    w: int
    h: int
    distortion: np.ndarray

    @property
    def name(self) -> str:
        """The camera name: the stem of ``file_path``."""
        return PurePosixPath(self.file_path.replace("\\", "/")).stem


def read_transforms(path: PathLike) -> list[NerfstudioFrame]:
    """Read ``transforms.json`` (a file, or the folder holding it), frames in file order.

    Raises:
        CaptureFormatError: naming ``frames[i].<key>`` for a missing key (absent from the frame and the
            top level), wrong shape, NaN/inf or non-rotation; the JSON line for a truncated file.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "transforms.json"
    meta = read_json(p)
    if not isinstance(meta, dict):
        raise CaptureFormatError(p, "(top level)", "expected an object with 'frames'")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CaptureFormatError(p, "frames", "expected a non-empty list of frames" if frames is not None else "missing")
    out = []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise CaptureFormatError(p, f"frames[{i}]", "expected an object")

        @no_type_check  # defined per frame: kept out of the test run's type checks (~1 ms per definition)
        def get(key: str, default=None):
            v = fr.get(key, meta.get(key, default))
            if v is None:
                raise CaptureFormatError(p, f"frames[{i}].{key}", "missing (in the frame and at the top level)")
            return v

        if "file_path" not in fr:
            raise CaptureFormatError(p, f"frames[{i}].file_path", "missing")
        M = require_array(p, f"frames[{i}].transform_matrix", get("transform_matrix"), (4, 4))
        require_rotation(p, f"frames[{i}].transform_matrix", M[:3, :3])
        if np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise CaptureFormatError(p, f"frames[{i}].transform_matrix", "expected a last row 0 0 0 1")
        intr = require_array(p, f"frames[{i}].fl_x/fl_y/cx/cy", [get(k) for k in _INTRINSICS[:4]], (4,))
        w, h = require_size(p, f"frames[{i}].w/h", get("w"), get("h"))
        dist = require_array(p, f"frames[{i}].k1..p2", [get(k, 0.0) for k in _DIST], (6,))
        if dist[3] != 0:
            raise CaptureFormatError(p, f"frames[{i}].k4", "expected 0: deliffas carries OpenCV's k1, k2, p1, p2, k3 only")
        model = fr.get("camera_model", meta.get("camera_model", "OPENCV"))
        if model not in PINHOLE_MODELS:
            where = f"frames[{i}].camera_model" if "camera_model" in fr else "camera_model"
            raise CaptureFormatError(p, where, f"expected one of {', '.join(PINHOLE_MODELS)} (a pinhole, with OpenCV "
                                               f"distortion), got {model!r}: deliffas cannot represent this lens; "
                                               "undistort the images to a pinhole first")
        out.append(NerfstudioFrame(str(fr["file_path"]), M, *intr, w, h, dist))
    require_unique_names(p, "frames[].file_path (camera names)", [f.name for f in out])
    return out


def write_transforms(path: PathLike, frames: Sequence[NerfstudioFrame]) -> Path:
    """Write ``transforms.json`` (``path`` a file, or a folder to hold it) with per-frame intrinsics.

    Distortion keys are written per frame only when non-zero; ``camera_model`` is ``OPENCV`` and
    ``applied_transform`` the identity (the file's world is the deliffas world, in metres).
    """
    p = Path(path)
    if p.is_dir() or p.suffix != ".json":
        p = p / "transforms.json"
    rows = []
    for f in frames:
        row = {"file_path": f.file_path, "transform_matrix": np.asarray(f.transform_matrix, np.float64).tolist(),
               "fl_x": float(f.fl_x), "fl_y": float(f.fl_y), "cx": float(f.cx), "cy": float(f.cy),
               "w": int(f.w), "h": int(f.h)}
        for k, v in zip(_DIST, np.asarray(f.distortion, np.float64)):
            if v != 0:
                row[k] = float(v)
        rows.append(row)
    write_json_atomic(p, {"camera_model": "OPENCV", "applied_transform": np.eye(4)[:3].tolist(), "frames": rows})
    return p


def nerfstudio_to_camera(frame: NerfstudioFrame) -> Camera:
    """The deliffas Camera: OpenGL camera-to-world in metres -> OpenCV world-to-camera in mm."""
    c2w_cv = np.asarray(frame.transform_matrix, np.float64) @ OPENGL_FROM_OPENCV  # y up/-z forward -> y down/+z
    K = np.array([[frame.fl_x, 0.0, frame.cx], [0.0, frame.fl_y, frame.cy], [0.0, 0.0, 1.0]])
    k1, k2, k3, _, p1, p2 = frame.distortion
    dist = np.array([k1, k2, p1, p2, k3])
    return to_camera(frame.name, K, invert_rigid(c2w_cv), frame.w, frame.h, units="m", pixel_centre="half",
                     distortion=dist if np.any(dist != 0) else None)


def camera_to_nerfstudio(camera: Camera, file_path: str | None = None, drop_distortion: bool = False) -> NerfstudioFrame:
    """The ``transforms.json`` frame of a deliffas Camera (``file_path`` default ``images/<name>.png``).

    Raises:
        ValueError: a K with skew (``transforms.json`` has none).
    """
    camera = require_distortion_fits(camera, "nerfstudio transforms.json", ("k1", "k2", "p1", "p2", "k3"), drop_distortion)
    K, E, (k1, k2, p1, p2, k3) = from_camera(camera, units="m", pixel_centre="half")
    if abs(K[0, 1]) > 1e-12:
        raise ValueError(f"camera {camera.name}: K has skew {K[0, 1]:g}; transforms.json cannot hold it")
    c2w_gl = invert_rigid(E) @ OPENGL_FROM_OPENCV
    return NerfstudioFrame(file_path or f"images/{camera.name}.png", c2w_gl, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                           camera.width, camera.height, np.array([k1, k2, k3, 0.0, p1, p2]))


# ----------------------------------------------------------------------------------- capture format
def _is_transforms(path: Path) -> bool:
    data = read_json(path)
    return isinstance(data, dict) and "frames" in data


FORMAT = CaptureFormat(
    "nerfstudio", "nerfstudio transforms.json", camera_path="transforms.json",
    distortion=("k1", "k2", "p1", "p2", "k3"), stores_size=True,
    detect_cameras=file_detector("transforms.json", suffixes=(".json",), accept=_is_transforms),
    read_cameras=lambda path, size: converted(in_folder(path, "transforms.json"), read_transforms(path),
                                              nerfstudio_to_camera),
    write_cameras=lambda cameras, out, options: write_transforms(
        out, [camera_to_nerfstudio(c, drop_distortion=options.drop_distortion) for c in cameras]))
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
