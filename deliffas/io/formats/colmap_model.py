"""The cameras and images of a COLMAP sparse model (``cameras``/``images`` as ``.bin`` or ``.txt``), read in Python.

Only what a camera rig needs is read: each camera's model, size and parameters, each image's pose,
camera and name (``points3D``, ``rigs`` and ``frames`` are not). deliffas parses these two files itself
instead of calling pycolmap's reader, which trusts the counts of a binary model: one damaged count made
it loop for minutes (found by fuzzing). Here every count is checked against the bytes that remain
before anything is read, and every error is a ``CaptureFormatError`` naming the file and the record.

Layouts (COLMAP documentation, "Output format"; little-endian binary):

- ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` per line; ``cameras.bin``: uint64 count,
  then per camera uint32 id, int32 model id, uint64 width, uint64 height, float64 params[n(model)].
- ``images.txt``: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``, then one line of 2D points (may be
  empty); ``images.bin``: uint64 count, then per image uint32 id, float64 qw qx qy qz tx ty tz, uint32
  camera id, NUL-terminated name, uint64 point count, per point float64 x, y and int64 point3D id.
- Lines starting with ``#`` and blank lines (outside the points line) are comments, as COLMAP reads them.

The quaternion is normalised on reading, as COLMAP does.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deliffas.io.infra.reader_checks import CaptureFormatError

__all__ = ["ColmapCamera", "ColmapImage", "CAMERA_MODELS", "read_colmap_model"]

CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}
"""COLMAP's camera model id -> (name, number of parameters) (``colmap/sensor/models.h``)."""
_BY_NAME = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}

_CAMERA_BYTES = 4 + 4 + 8 + 8  # the smallest camera record of cameras.bin (parameters come on top)
_IMAGE_BYTES = 4 + 7 * 8 + 4 + 1 + 8  # the smallest image record of images.bin (empty name, no points)
_POINT2D_BYTES = 8 + 8 + 8


@dataclass(frozen=True)
class ColmapCamera:
    """One camera of ``cameras.bin``/``.txt``: its model name, image size in pixels and parameters (finite)."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass(frozen=True)
class ColmapImage:
    """One image of ``images.bin``/``.txt``: ``cam_from_world`` as a unit quaternion (w, x, y, z) and a translation."""

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str


def _camera(path: Path, key: str, camera_id: int, model: str, width: int, height: int, params) -> ColmapCamera:
    n = _BY_NAME[model][1]
    if len(params) != n:
        raise CaptureFormatError(path, key, f"expected {n} parameters for {model}, got {len(params)}")
    if width <= 0 or height <= 0:
        raise CaptureFormatError(path, key, f"expected a positive image size, got {width} x {height}")
    p = np.array(params, np.float64)
    if not np.isfinite(p).all():
        raise CaptureFormatError(path, key, "expected finite parameters, got NaN or inf")
    return ColmapCamera(camera_id, model, int(width), int(height), p)


def _image(path: Path, key: str, image_id: int, q, t, camera_id: int, name: str) -> ColmapImage:
    q, t = np.array(q, np.float64), np.array(t, np.float64)
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise CaptureFormatError(path, key, "expected a finite pose (QW QX QY QZ TX TY TZ), got NaN or inf")
    norm = float(np.sqrt((q * q).sum()))
    if not 1e-12 < norm < np.inf:
        raise CaptureFormatError(path, key, f"expected a rotation quaternion, got one of norm {norm:g}")
    if not name:
        raise CaptureFormatError(path, key, "expected an image name, got an empty one")
    return ColmapImage(image_id, q / norm, t, camera_id, name)


def _add(path: Path, table: dict, key: str, record) -> None:
    rid = record.camera_id if isinstance(record, ColmapCamera) else record.image_id
    if rid in table:
        raise CaptureFormatError(path, key, f"id {rid} appears twice")
    table[rid] = record


class _Binary:
    """A cursor over a binary model file that never reads past its end."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def take(self, fmt: str, key: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise CaptureFormatError(self.path, key, f"expected {size} more bytes at offset {self.pos}, the file ends "
                                                     f"at {len(self.data)} (truncated?)")
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return out

    def count(self, key: str, record_bytes: int) -> int:
        (n,) = self.take("<Q", key)
        left = len(self.data) - self.pos
        if n > left // record_bytes:
            raise CaptureFormatError(self.path, key, f"{n} records of at least {record_bytes} bytes do not fit in the "
                                                     f"{left} bytes that follow")
        return n

    def name(self, key: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise CaptureFormatError(self.path, key, "expected a NUL-terminated name, the file ends first")
        raw, self.pos = self.data[self.pos:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise CaptureFormatError(self.path, key, f"expected a UTF-8 name, got {raw[:40]!r}") from None

    def end(self) -> None:
        if self.pos != len(self.data):
            raise CaptureFormatError(self.path, "end", f"expected the file to end after the last record, got "
                                                       f"{len(self.data) - self.pos} more bytes")


def _cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    f, out = _Binary(path), {}
    for i in range(f.count("count", _CAMERA_BYTES)):
        key = f"camera {i + 1}"
        cid, model_id, width, height = f.take("<IiQQ", key)
        if model_id not in CAMERA_MODELS:
            raise CaptureFormatError(path, key, f"unknown camera model id {model_id}")
        model, n = CAMERA_MODELS[model_id]
        _add(path, out, key, _camera(path, key, cid, model, width, height, f.take(f"<{n}d", key)))
    f.end()
    return out


def _images_bin(path: Path) -> dict[int, ColmapImage]:
    f, out = _Binary(path), {}
    for i in range(f.count("count", _IMAGE_BYTES)):
        key = f"image {i + 1}"
        iid, qw, qx, qy, qz, tx, ty, tz, cid = f.take("<I7dI", key)
        name = f.name(key)
        npts = f.count(f"{key}: points", _POINT2D_BYTES)
        f.pos += npts * _POINT2D_BYTES  # the 2D points are not needed for a camera rig
        _add(path, out, key, _image(path, key, iid, (qw, qx, qy, qz), (tx, ty, tz), cid, name))
    f.end()
    return out


def _text_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").split("\n")
    except UnicodeDecodeError:
        raise CaptureFormatError(path, "text", "expected UTF-8 text, got binary bytes") from None


def _numbers(path: Path, key: str, tokens: list[str], kind: type) -> list:
    try:
        return [kind(t) for t in tokens]
    except ValueError:
        raise CaptureFormatError(path, key, f"expected {kind.__name__} values, got {' '.join(tokens)[:80]!r}") from None


def _cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    out = {}
    for lineno, line in enumerate(_text_lines(path), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key = f"line {lineno}"
        tok = line.split()
        if len(tok) < 4 or tok[1] not in _BY_NAME:
            raise CaptureFormatError(path, key, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] with a known model, "
                                                f"got {line[:80]!r}")
        cid, width, height = _numbers(path, key, [tok[0], tok[2], tok[3]], int)
        _add(path, out, key, _camera(path, key, cid, tok[1], width, height, _numbers(path, key, tok[4:], float)))
    return out


def _images_txt(path: Path) -> dict[int, ColmapImage]:
    out, lines, i = {}, _text_lines(path), 0
    while i < len(lines):
        line, lineno = lines[i].strip(), i + 1
        i += 1
        if not line or line.startswith("#"):
            continue
        key = f"line {lineno}"
        tok = line.split()
        if len(tok) != 10:
            raise CaptureFormatError(path, key, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (a name without "
                                                f"spaces), got {len(tok)} fields")
        iid, cid = _numbers(path, key, [tok[0], tok[8]], int)
        pose = _numbers(path, key, tok[1:8], float)
        _add(path, out, key, _image(path, key, iid, pose[:4], pose[4:], cid, tok[9]))
        i += 1  # the image's line of 2D points, not needed for a camera rig
    return out


def read_colmap_model(model_dir: str | os.PathLike) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage]]:
    """The cameras and images of the COLMAP model in ``model_dir`` (binary when ``cameras.bin`` is there, else text).

    Returns:
        camera id -> camera, image id -> image.

    Raises:
        FileNotFoundError: ``model_dir`` is not a folder.
        CaptureFormatError: no model files, or a malformed record (named by file and record), a duplicate id,
            an image whose camera is missing, or no images.
    """
    d = Path(model_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: COLMAP model folder not found")
    ext = ".bin" if (d / "cameras.bin").is_file() else ".txt"
    if not (d / f"cameras{ext}").is_file():
        raise CaptureFormatError(d, "cameras.bin", "not a COLMAP model (no cameras.bin or cameras.txt)")
    if not (d / f"images{ext}").is_file():
        raise CaptureFormatError(d / f"images{ext}", "file", f"not found (a COLMAP model has one beside cameras{ext})")
    if ext == ".bin":
        cameras, images = _cameras_bin(d / "cameras.bin"), _images_bin(d / "images.bin")
    else:
        cameras, images = _cameras_txt(d / "cameras.txt"), _images_txt(d / "images.txt")
    for img in images.values():
        if img.camera_id not in cameras:
            raise CaptureFormatError(d / f"images{ext}", f"image {img.image_id}",
                                     f"camera {img.camera_id} is not in cameras{ext}")
    if not images:
        raise CaptureFormatError(d / f"images{ext}", "images", "the COLMAP model has no images")
    return cameras, images
