"""Pose2Sim / anipose / FreeMoCap ``Calib.toml`` cameras (aniposelib's ``CameraGroup.dump`` layout) as deliffas Cameras.

Layout (Pose2Sim ``common.retrieve_calib_params`` and aniposelib, which writes it): one TOML table
per camera (any key but ``metadata``, ``capture_volume``, ``charuco``, ``checkerboard``) with

- ``name``: the camera's name; ``size = [width, height]`` in pixels;
- ``matrix``: (3, 3) K in **OpenCV** pixels (centres on integers: ``cv2.projectPoints``);
- ``distortions``: OpenCV (k1, k2, p1, p2) or (k1, k2, p1, p2, k3); ``fisheye = true`` is another lens
  model and is refused;
- ``rotation``: Rodrigues vector and ``translation``: the **world -> camera** pose of OpenCV
  (x_cam = R X + t), translation in **metres** (Pose2Sim's unit).

anipose and FreeMoCap write the translation in the unit of their calibration board (usually mm). Such
a file would read a thousand times too large, so a camera centre more than ``MAX_CENTRE_M`` from the
origin is refused, naming the camera, rather than read.

The module defines ``FORMAT`` (name ``pose2sim``), registered by ``deliffas.io.formats.builtin``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.camera_conventions import (from_camera, matrix_to_rotvec, require_distortion_fits, rotvec_to_matrix,
                                            to_camera)
from deliffas.io.cameras import Camera
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.formats.camera_files import file_detector, in_folder
from deliffas.io.infra.files import write_bytes_atomic
from deliffas.io.infra.reader_checks import CaptureFormatError, naming_file, require_array, require_size

__all__ = ["FORMAT", "NOT_CAMERAS", "MAX_CENTRE_M", "read_calib_toml", "write_calib_toml"]

NOT_CAMERAS = ("metadata", "capture_volume", "charuco", "checkerboard")
"""Tables of a ``Calib.toml`` that are not cameras (Pose2Sim skips the same)."""

MAX_CENTRE_M = 1000.0
"""A camera centre farther than this from the origin (m) is a millimetre file read as metres: refused."""


def _load_toml(path: Path) -> dict:
    try:
        import tomllib  # Python >= 3.11; imported here: only this format reads TOML
    except ModuleNotFoundError:  # Python 3.10
        try:
            import tomli as tomllib
        except ModuleNotFoundError:
            raise CaptureFormatError(path, "file", "reading TOML needs Python >= 3.11 or: pip install tomli") from None
    if not path.is_file():
        raise CaptureFormatError(path, "file", "not found")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise CaptureFormatError(path, "file", f"expected TOML, got {err}") from None


def _camera(path: Path, key: str, table: dict) -> Camera:
    name = str(table.get("name", key))
    if table.get("fisheye", False):
        raise CaptureFormatError(path, f"{key}.fisheye", "fisheye lenses are not supported (OpenCV pinhole + "
                                                         "distortion only); undistort the images first")
    size = table.get("size")
    if not isinstance(size, list) or len(size) != 2:
        raise CaptureFormatError(path, f"{key}.size", f"expected [width, height], got {size!r}")
    w, h = require_size(path, f"{key}.size", *size)
    K = require_array(path, f"{key}.matrix", table.get("matrix"), (3, 3))
    dist = np.ravel(require_array(path, f"{key}.distortions", table.get("distortions", [0, 0, 0, 0]), (-1,)))
    if len(dist) not in (4, 5):
        raise CaptureFormatError(path, f"{key}.distortions", f"expected 4 or 5 OpenCV coefficients, got {len(dist)}")
    rvec = require_array(path, f"{key}.rotation", table.get("rotation"), (3,))
    t = require_array(path, f"{key}.translation", table.get("translation"), (3,))
    E = np.eye(4)
    E[:3, :3] = rotvec_to_matrix(rvec)
    E[:3, 3] = t
    centre = -E[:3, :3].T @ t
    if np.linalg.norm(centre) > MAX_CENTRE_M:
        raise CaptureFormatError(path, f"{key}.translation", f"expected metres (Pose2Sim), got a camera centre "
                                 f"{np.linalg.norm(centre):.4g} m from the origin: a file in millimetres "
                                 f"(anipose/FreeMoCap board units)? divide its translations by 1000")
    with naming_file(path, key):
        return to_camera(name, K, E, w, h, units="m", pixel_centre="integer", distortion=dist)


def read_calib_toml(path: str | os.PathLike) -> list[Camera]:
    """The cameras of a ``Calib.toml`` (or of ``Calib.toml`` in a folder), in the file's order.

    Raises:
        CaptureFormatError: a missing or malformed file, naming the camera table and key.
    """
    p = in_folder(Path(path), "Calib.toml")
    doc = _load_toml(p)
    tables = [(k, v) for k, v in doc.items() if k not in NOT_CAMERAS and isinstance(v, dict)]
    if not tables:
        raise CaptureFormatError(p, "file", "expected at least one camera table ([cam_1] ...), got none")
    return [_camera(p, k, v) for k, v in tables]


def _numbers(values) -> str:
    return "[ " + ", ".join(repr(float(v)) for v in values) + ",]"


def write_calib_toml(path: str | os.PathLike, cameras: Sequence[Camera], drop_distortion: bool = False) -> Path:
    """Write ``cameras`` as a Pose2Sim ``Calib.toml`` (tables ``cam_1``..., translation in metres), atomically.

    Raises:
        LossyConversionError: DynaCap's ``radial`` coefficient (unless ``drop_distortion``).
        ValueError: a camera with skew (the matrix Pose2Sim builds has none).
    """
    p = Path(path)
    blocks = []
    for i, cam in enumerate(cameras):
        cam = require_distortion_fits(cam, "Calib.toml", ("k1", "k2", "p1", "p2", "k3"), drop_distortion)
        K, E, dist = from_camera(cam, units="m", pixel_centre="integer")
        if K[0, 1] != 0:
            raise ValueError(f"camera {cam.name}: skew {K[0, 1]:g} cannot be written to Calib.toml")
        blocks.append("\n".join([
            f"[cam_{i + 1}]", f"name = {_quoted(cam.name)}", f"size = {_numbers([cam.width, cam.height])}",
            "matrix = [ " + ", ".join(_numbers(row) for row in K) + ",]",
            f"distortions = {_numbers(dist if dist[4] != 0 else dist[:4])}",
            f"rotation = {_numbers(matrix_to_rotvec(E[:3, :3]))}", f"translation = {_numbers(E[:3, 3])}",
            "fisheye = false"]))
    text = "\n\n".join(blocks) + "\n\n[metadata]\nadjusted = false\nerror = 0.0\n"
    p.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(p, text.encode("utf-8"))
    return p


def _quoted(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _is_calib_toml(path: Path) -> bool:
    try:
        doc = _load_toml(path)
    except CaptureFormatError:
        return False
    return any(isinstance(v, dict) and "matrix" in v for k, v in doc.items() if k not in NOT_CAMERAS)


FORMAT = CaptureFormat(
    "pose2sim", "Pose2Sim / anipose / FreeMoCap Calib.toml", camera_path="Calib.toml",
    distortion=("k1", "k2", "p1", "p2", "k3"), stores_size=True,
    detect_cameras=file_detector("Calib.toml", suffixes=(".toml",), accept=_is_calib_toml),
    read_cameras=lambda path, size: read_calib_toml(path),
    write_cameras=lambda cameras, out, options: write_calib_toml(out, cameras, options.drop_distortion))
"""The ``Calib.toml`` cameras, registered by ``deliffas.io.formats.builtin``."""
