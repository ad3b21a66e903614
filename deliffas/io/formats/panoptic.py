"""CMU Panoptic Studio ``calibration_<seq>.json`` cameras (VGA, HD and Kinect colour) as deliffas Cameras.

Conventions, worked out from the Panoptic Studio toolbox (CMU-Perceptual-Computing-Lab/panoptic-toolbox,
``panutils.projectPoints``), which publishes the dataset: ``{"cameras": [...]}``, each camera with

- ``name`` (``"<panel>_<node>"``, e.g. ``00_03``), ``type`` (``vga``, ``hd``, ``kinect-color``),
  ``resolution`` = [width, height] in pixels;
- ``K``: (3, 3) in **OpenCV** pixels (the toolbox multiplies normalised points by K, centres on integers);
- ``distCoef``: OpenCV (k1, k2, p1, p2, k3);
- ``R`` (3, 3) and ``t`` (3, 1): world -> camera, x_cam = R X + t, in **centimetres** (the dataset's
  world unit).

Every camera is read, whatever its type, in the file's order; written cameras get type ``hd``, panel 0
and node = their index. The module defines ``FORMAT`` (name ``panoptic``), registered by
``deliffas.io.formats.builtin``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.camera_conventions import from_camera, require_distortion_fits, to_camera
from deliffas.io.cameras import Camera
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.infra.reader_checks import (CaptureFormatError, naming_file, read_json, require_array, require_size,
                                             write_json_atomic)

__all__ = ["FORMAT", "MM_PER_CM", "read_panoptic_calibration", "write_panoptic_calibration"]

MM_PER_CM = 10.0
"""Panoptic translations are centimetres; deliffas worlds are millimetres."""


def _camera(path: Path, i: int, cam) -> Camera:
    if not isinstance(cam, dict):
        raise CaptureFormatError(path, f"cameras[{i}]", f"expected an object, got {type(cam).__name__}")
    name = str(cam.get("name", i))
    key = f"camera {name}"
    res = cam.get("resolution")
    if not isinstance(res, list) or len(res) != 2:
        raise CaptureFormatError(path, f"{key}.resolution", f"expected [width, height], got {res!r}")
    w, h = require_size(path, f"{key}.resolution", *res)
    K = require_array(path, f"{key}.K", cam.get("K"), (3, 3))
    dist = np.ravel(require_array(path, f"{key}.distCoef", cam.get("distCoef", [0.0] * 5), (-1,)))
    if len(dist) > 5:
        raise CaptureFormatError(path, f"{key}.distCoef", f"expected at most 5 OpenCV coefficients, got {len(dist)}")
    E = np.eye(4)
    E[:3, :3] = require_array(path, f"{key}.R", cam.get("R"), (3, 3))
    E[:3, 3] = require_array(path, f"{key}.t", cam.get("t"), (3, 1), reshape=True).ravel() * MM_PER_CM
    with naming_file(path, key):
        return to_camera(name, K, E, w, h, units="mm", pixel_centre="integer", distortion=dist)


def _calibration_file(path: Path) -> Path | None:
    """``path`` itself, or the one ``calibration_*.json`` in a folder (None when there is none)."""
    if not path.is_dir():
        return path
    found = sorted(path.glob("calibration_*.json"))
    return found[0] if found else None


def read_panoptic_calibration(path: str | os.PathLike) -> list[Camera]:
    """The cameras of a ``calibration_<seq>.json`` (or of the one in a folder).

    Raises:
        CaptureFormatError: a missing or malformed file, naming the camera and key.
    """
    p = _calibration_file(Path(path)) or Path(path) / "calibration_<seq>.json"
    doc = read_json(p)
    cams = doc.get("cameras") if isinstance(doc, dict) else None
    if not isinstance(cams, list) or not cams:
        raise CaptureFormatError(p, "cameras", "expected a non-empty list of cameras")
    return [_camera(p, i, c) for i, c in enumerate(cams)]


def write_panoptic_calibration(path: str | os.PathLike, cameras: Sequence[Camera],
                               drop_distortion: bool = False) -> Path:
    """Write ``cameras`` as a Panoptic ``calibration_<seq>.json`` (cm, type ``hd``), atomically.

    Raises:
        LossyConversionError: DynaCap's ``radial`` coefficient (unless ``drop_distortion``).
    """
    out = []
    for i, cam in enumerate(cameras):
        cam = require_distortion_fits(cam, "Panoptic calibration", ("k1", "k2", "p1", "p2", "k3"), drop_distortion)
        K, E, dist = from_camera(cam, units="mm", pixel_centre="integer")
        out.append({"name": cam.name, "type": "hd", "resolution": [cam.width, cam.height], "panel": 0, "node": i,
                    "K": K.tolist(), "distCoef": dist.tolist(), "R": E[:3, :3].tolist(),
                    "t": (E[:3, 3:] / MM_PER_CM).tolist()})
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(p, {"calibDataSource": "deliffas", "cameras": out})
    return p


def _detect(path: Path) -> bool:
    p = _calibration_file(Path(path))
    if p is None or not (p.is_file() and p.name.startswith("calibration_") and p.suffix == ".json"):
        return False
    try:
        doc = read_json(p)
    except CaptureFormatError:
        return False
    return isinstance(doc, dict) and isinstance(doc.get("cameras"), list)


FORMAT = CaptureFormat(
    "panoptic", "CMU Panoptic calibration_<seq>.json", camera_path="calibration_panoptic.json",
    distortion=("k1", "k2", "p1", "p2", "k3"), stores_size=True, detect_cameras=_detect,
    read_cameras=lambda path, size: read_panoptic_calibration(path),
    write_cameras=lambda cameras, out, options: write_panoptic_calibration(out, cameras, options.drop_distortion))
"""The Panoptic cameras, registered by ``deliffas.io.formats.builtin``."""
