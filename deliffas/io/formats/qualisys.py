"""Qualisys Track Manager ``.qca.txt`` calibrations (XML), read and written as Pose2Sim reads them.

Conventions, worked out from Pose2Sim (perfanalytics/pose2sim, ``calibration.read_qca`` and
``calib_qca_fun``), which converts these files for markerless capture:

- cameras: every ``cameras/camera`` whose ``model`` is ``Miqus Video``, ``Miqus Video UnderWater`` or
  ``none`` (marker-only cameras are left out), named by ``serial``, in natural order of the names;
- image: ``fov_video`` is the pixel rectangle, inclusive: width = right - left + 1, height = bottom - top + 1;
- intrinsics in **sensor units, 64 per pixel**: fx = ``focalLengthU`` / 64, cx = ``centerPointU`` / 64 -
  ``fov_video.left`` (OpenCV pixels, centres on integers), likewise V; the lens terms
  ``radialDistortion1..3`` (k1, k2, k3) and ``tangentalDistortion1..2`` (p1, p2) are divided by 64 too
  (Pose2Sim leaves out ``radialDistortion3``; it is read the same way here, and written 0 when zero);
  a ``video_resolution`` of e.g. ``720p`` scales pixels by 720 / 1080; ``skew`` must be 0;
- pose: ``transform`` holds the camera position (x, y, z) in **mm** and a rotation M (r11 .. r33, row
  by row) that takes world directions into Qualisys camera axes (looking along -z, y up); OpenCV axes
  are those turned 180 degrees about x, so world -> camera is R = diag(1, -1, -1) M, t = -R (x, y, z).

The module defines ``FORMAT`` (name ``qualisys``), registered by ``deliffas.io.formats.builtin``.
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.camera_conventions import from_camera, require_distortion_fits, to_camera
from deliffas.io.cameras import Camera
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.formats.camera_files import file_detector
from deliffas.io.infra.files import write_bytes_atomic
from deliffas.io.infra.reader_checks import CaptureFormatError, naming_file, require_numbers

__all__ = ["FORMAT", "SENSOR_UNITS_PER_PIXEL", "VIDEO_MODELS", "read_qca", "write_qca"]

SENSOR_UNITS_PER_PIXEL = 64.0
"""Qualisys intrinsics (and, as Pose2Sim reads them, lens terms) are stored in 1/64 pixel units."""

VIDEO_MODELS = ("Miqus Video", "Miqus Video UnderWater", "none")
"""Camera models Pose2Sim reads as video cameras; others (marker cameras) are left out."""

QUALISYS_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])
"""Qualisys camera axes (y up, looking along -z) from OpenCV's (y down, +z forward); its own inverse."""

_ROTATION_KEYS = [f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
_LENS_KEYS = ("radialDistortion1", "radialDistortion2", "tangentalDistortion1", "tangentalDistortion2",
              "radialDistortion3")  # OpenCV order k1, k2, p1, p2, k3


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _numbers(path: Path, key: str, element: ET.Element | None, names: Sequence[str]) -> np.ndarray:
    if element is None:
        raise CaptureFormatError(path, key, "missing")
    missing = [n for n in names if n not in element.attrib]
    if missing:
        raise CaptureFormatError(path, f"{key}.{missing[0]}", "missing")
    try:
        values = [float(element.attrib[n]) for n in names]
    except ValueError:
        raise CaptureFormatError(path, key, f"expected numbers in {', '.join(names)}") from None
    return require_numbers(path, key, values)


def _camera(path: Path, tag: ET.Element) -> Camera:
    name = tag.attrib.get("serial", "")
    key = f"camera {name}"
    left, top, right, bottom = _numbers(path, f"{key} fov_video", tag.find("fov_video"),
                                        ("left", "top", "right", "bottom"))
    res = tag.attrib.get("video_resolution")
    scale = 1.0
    if res is not None:
        if not re.fullmatch(r"\d+p", res):
            raise CaptureFormatError(path, f"{key} video_resolution", f"expected e.g. 1080p, got {res!r}")
        scale = int(res[:-1]) / 1080
    intr = tag.find("intrinsic")
    fu, fv, cu, cv, skew = _numbers(path, f"{key} intrinsic", intr,
                                    ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV", "skew"))
    if skew != 0:
        raise CaptureFormatError(path, f"{key} intrinsic.skew", f"expected 0 (Pose2Sim ignores skew), got {skew:g}")
    lens = _numbers(path, f"{key} intrinsic", intr, _LENS_KEYS) / SENSOR_UNITS_PER_PIXEL
    u = SENSOR_UNITS_PER_PIXEL
    K = np.array([[fu / u * scale, 0.0, (cu / u - left) * scale], [0.0, fv / u * scale, (cv / u - top) * scale],
                  [0.0, 0.0, 1.0]])
    tr = _numbers(path, f"{key} transform", tag.find("transform"), [*_ROTATION_KEYS, "x", "y", "z"])
    R = QUALISYS_FROM_OPENCV @ tr[:9].reshape(3, 3)
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = -R @ tr[9:]
    width, height = (right - left + 1) * scale, (bottom - top + 1) * scale
    if not (float(width).is_integer() and float(height).is_integer() and width > 0 and height > 0):
        raise CaptureFormatError(path, f"{key} fov_video", f"expected a positive whole-pixel size, got {width} x {height}")
    with naming_file(path, key):
        return to_camera(name, K, E, int(width), int(height), units="mm", pixel_centre="integer", distortion=lens)


def read_qca(path: str | os.PathLike) -> list[Camera]:
    """The video cameras of a ``.qca.txt`` file, in natural order of their serials.

    Raises:
        CaptureFormatError: a missing or malformed file, naming the camera and the element.
    """
    p = Path(path)
    if not p.is_file():
        raise CaptureFormatError(p, "file", "not found")
    try:
        root = ET.fromstring(p.read_bytes())
    except (ET.ParseError, LookupError) as err:  # LookupError: an XML declaration naming an unknown encoding
        raise CaptureFormatError(p, "file", f"expected Qualisys XML, got {err}") from None
    tags = [t for t in root.findall("cameras/camera") if t.attrib.get("model") in VIDEO_MODELS]
    if not tags:
        raise CaptureFormatError(p, "cameras", f"expected at least one video camera (model {', '.join(VIDEO_MODELS)})")
    return [_camera(p, t) for t in sorted(tags, key=lambda t: _natural_key(t.attrib.get("serial", "")))]


def _num(value) -> str:
    return repr(float(value))


def _camera_element(parent: ET.Element, cam: Camera, drop_distortion: bool) -> None:
    cam = require_distortion_fits(cam, "Qualisys .qca.txt", ("k1", "k2", "p1", "p2", "k3"), drop_distortion)
    K, E, dist = from_camera(cam, units="mm", pixel_centre="integer")
    if K[0, 1] != 0:
        raise ValueError(f"camera {cam.name}: skew {K[0, 1]:g} cannot be written to a .qca.txt")
    M = QUALISYS_FROM_OPENCV @ E[:3, :3]
    centre = -E[:3, :3].T @ E[:3, 3]
    u = SENSOR_UNITS_PER_PIXEL
    tag = ET.SubElement(parent, "camera", active="1", model="none", serial=cam.name, viewrotation="0")
    fov = {"left": "0", "top": "0", "right": str(cam.width - 1), "bottom": str(cam.height - 1)}
    for name in ("fov_marker", "fov_marker_max", "fov_video", "fov_video_max"):
        ET.SubElement(tag, name, fov)
    ET.SubElement(tag, "transform", {**{k: _num(v) for k, v in zip(_ROTATION_KEYS, M.ravel())},
                                     **{k: _num(v) for k, v in zip("xyz", centre)}})
    ET.SubElement(tag, "intrinsic", {
        "focalLengthU": _num(K[0, 0] * u), "focalLengthV": _num(K[1, 1] * u), "centerPointU": _num(K[0, 2] * u),
        "centerPointV": _num(K[1, 2] * u), "skew": "0", "sensorMinU": "0", "sensorMinV": "0",
        "sensorMaxU": _num((cam.width - 1) * u), "sensorMaxV": _num((cam.height - 1) * u),
        **{k: _num(v * u) for k, v in zip(_LENS_KEYS, dist)}})


def write_qca(path: str | os.PathLike, cameras: Sequence[Camera], drop_distortion: bool = False) -> Path:
    """Write ``cameras`` as a ``.qca.txt`` (video cameras, model ``none``, full-sensor fov), atomically.

    Raises:
        LossyConversionError: DynaCap's ``radial`` coefficient (unless ``drop_distortion``).
        ValueError: a camera with skew.
    """
    root = ET.Element("calibration", type="regular", source="deliffas")
    cams = ET.SubElement(root, "cameras")
    for cam in cameras:
        _camera_element(cams, cam, drop_distortion)
    ET.indent(root)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(p, ET.tostring(root, encoding="utf-8", xml_declaration=True) + b"\n")
    return p


FORMAT = CaptureFormat(
    "qualisys", "Qualisys .qca.txt (as Pose2Sim reads it)", camera_path="Calib.qca.txt",
    distortion=("k1", "k2", "p1", "p2", "k3"), stores_size=True, detect_cameras=file_detector("Calib.qca.txt", suffixes=(".qca.txt",)),
    read_cameras=lambda path, size: read_qca(path),
    write_cameras=lambda cameras, out, options: write_qca(out, cameras, options.drop_distortion))
"""The ``.qca.txt`` cameras, registered by ``deliffas.io.formats.builtin``."""
