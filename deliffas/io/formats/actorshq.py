"""ActorsHQ ``calibration.csv`` cameras and the rgbs/masks file layout as plain records.

Conventions, worked out from HumanRF (synthesiaresearch/humanrf @c0c1fb7), which publishes ActorsHQ:

- ``actorshq/dataset/camera_data.py``: columns ``name, w, h, rx, ry, rz, tx, ty, tz, fx, fy, px, py``
  (``write_calibration_csv``); ``CameraData`` also has optional radial ``k1, k2, k3`` (default 0),
  which we read and write as extra columns when present (HumanRF's ``csv.DictReader`` ignores them).
- Pose: **camera-to-world**, "world_space = Rotation @ camera_space + Translation" with ``rx, ry, rz``
  an axis-angle vector (radians = its norm); camera axes right-down-forward "similarly to COLMAP"
  (OpenCV axes). deliffas inverts it (``invert_rigid``).
- Units: "translation is typically stored in meters [m]"; deliffas x 1000.
- Intrinsics are **normalised** by the image size: fx_pixel = w * fx, cx_pixel = w * px,
  fy_pixel = h * fy, cy_pixel = h * py (``CameraData.fx_pixel`` ...; Animatable Gaussians reads them the
  same way). Downscaled copies (``1x``/``2x``/``4x`` folders) keep the normalised values and change w, h.
- Pixels: HumanRF samples pixel (x, y) at (x + 0.5, y + 0.5) (``dataset/native/ray_sampler.cu``) and
  exports K to COLMAP unchanged (``toolbox/export_colmap.py``): the deliffas convention, K is copied.
- Distortion: radial k1, k2, k3 in the OpenCV sense (tangential p1, p2 has no column: the writer
  refuses it unless dropped).
- Layout (``dataset/volumetric_dataset.py``): ``rgbs/<cam>/<cam>_rgb<frame:06d>.jpg``,
  ``masks/<cam>/<cam>_mask<frame:06d>.png``, ``calibration.csv`` beside them; frames 0-based.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, no_type_check

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.camera_conventions import (from_camera, invert_rigid, matrix_to_rotvec, require_distortion_fits,
                                            rotvec_to_matrix, to_camera)
from deliffas.io.infra.reader_checks import (CaptureFormatError, require_array, require_rotation, require_size,
                                             require_unique_names)
from deliffas.io.infra.files import durable_replace, temp_path
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.formats.camera_files import converted, file_detector, in_folder

__all__ = [
    "ActorsHQCamera",
    "ACTORSHQ_COLUMNS",
    "read_actorshq_calibration",
    "write_actorshq_calibration",
    "actorshq_to_camera",
    "camera_to_actorshq",
    "actorshq_rgb_path",
    "actorshq_mask_path",
]

PathLike = str | os.PathLike

ACTORSHQ_COLUMNS = ("name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py")
"""The columns HumanRF's ``write_calibration_csv`` writes, in order."""

_RADIAL = ("k1", "k2", "k3")


@dataclass(frozen=True)
class ActorsHQCamera:
    """One row of ``calibration.csv``, in the file's conventions.

    Attributes:
        name: the ``name`` column (``Cam001``).
        width: ``w``, pixels.
        height: ``h``, pixels.
        rotation_axisangle: (3,) float64 camera -> world rotation, axis-angle radians.
        translation: (3,) float64 camera centre in the world, metres.
        focal_length: (2,) float64 (fx / w, fy / h), normalised.
        principal_point: (2,) float64 (cx / w, cy / h), normalised, pixel centres at +0.5.
        radial: (3,) float64 (k1, k2, k3), zeros when the file has no such columns.
    """

    name: str
    width: int
    height: int
    rotation_axisangle: np.ndarray
    translation: np.ndarray
    focal_length: np.ndarray
    principal_point: np.ndarray
    radial: np.ndarray


def read_actorshq_calibration(path: PathLike) -> list[ActorsHQCamera]:
    """Read ``calibration.csv`` (a file, or the folder holding it), in row order.

    Raises:
        CaptureFormatError: naming ``row <i>: <column>`` for a missing column or value, a non-number,
            NaN/inf or a bad size; the header for missing columns.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "calibration.csv"
    if not p.is_file():
        raise CaptureFormatError(p, "file", "not found")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise CaptureFormatError(p, "CSV", "expected UTF-8 text, got binary bytes") from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    header = reader.fieldnames or []
    missing = [c for c in ACTORSHQ_COLUMNS if c not in header]
    if missing:
        raise CaptureFormatError(p, f"header column {missing[0]}", f"missing (expected columns {', '.join(ACTORSHQ_COLUMNS)})")
    out = []
    for i, row in enumerate(reader, start=1):
        @no_type_check  # defined per row: kept out of the test run's type checks (~1 ms per definition)
        def num(col: str, required: bool = True) -> float:
            v = row.get(col)
            if v is None or v == "":
                if required:
                    raise CaptureFormatError(p, f"row {i}: {col}", "missing (the row is short or truncated)")
                return 0.0
            try:
                return float(v)
            except ValueError:
                raise CaptureFormatError(p, f"row {i}: {col}", f"expected a number, got {v[:30]!r}") from None

        vals = {c: num(c) for c in ACTORSHQ_COLUMNS[1:]}
        name = row["name"]
        if not name:
            raise CaptureFormatError(p, f"row {i}: name", "missing")
        w, h = require_size(p, f"row {i}: w/h", vals["w"], vals["h"])
        rot = require_array(p, f"row {i}: rx/ry/rz", [vals["rx"], vals["ry"], vals["rz"]], (3,))
        t = require_array(p, f"row {i}: tx/ty/tz", [vals["tx"], vals["ty"], vals["tz"]], (3,))
        f = require_array(p, f"row {i}: fx/fy", [vals["fx"], vals["fy"]], (2,))
        c = require_array(p, f"row {i}: px/py", [vals["px"], vals["py"]], (2,))
        k = require_array(p, f"row {i}: k1/k2/k3", [num(n, required=False) for n in _RADIAL], (3,))
        if np.any(f == 0):
            raise CaptureFormatError(p, f"row {i}: fx/fy", "expected non-zero normalised focal lengths")
        out.append(ActorsHQCamera(name, w, h, rot, t, f, c, k))
    if not out:
        raise CaptureFormatError(p, "rows", "expected at least one camera row, got none")
    require_unique_names(p, "name", [c.name for c in out])
    return out


def write_actorshq_calibration(path: PathLike, cameras: Sequence[ActorsHQCamera]) -> Path:
    """Write ``calibration.csv`` (``path`` a file, or a folder to hold it), full precision, atomically.

    The ``k1, k2, k3`` columns are added only when some camera has radial distortion.
    """
    p = Path(path)
    if p.is_dir() or p.suffix != ".csv":
        p = p / "calibration.csv"
    radial = any(np.any(np.asarray(c.radial) != 0) for c in cameras)
    cols = ACTORSHQ_COLUMNS + (_RADIAL if radial else ())
    buf = io.StringIO(newline="")
    w = csv.writer(buf, lineterminator="\r\n")  # csv.DictWriter's default line end, as HumanRF writes
    w.writerow(cols)
    for c in cameras:
        row = [c.name, int(c.width), int(c.height), *map(repr, map(float, c.rotation_axisangle)),
               *map(repr, map(float, c.translation)), *map(repr, map(float, c.focal_length)),
               *map(repr, map(float, c.principal_point))]
        if radial:
            row += [repr(float(v)) for v in c.radial]
        w.writerow(row)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(p)
    with open(tmp, "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())
    durable_replace(tmp, p)
    return p


def actorshq_to_camera(cam: ActorsHQCamera, path: PathLike = "calibration.csv") -> Camera:
    """The deliffas Camera: world -> camera (inverted), mm, K in pixels (unchanged pixel centres).

    Raises:
        CaptureFormatError: the axis-angle vector is not finite (named with ``path``).
    """
    c2w = np.eye(4)
    c2w[:3, :3] = require_rotation(path, f"{cam.name}: rx/ry/rz", rotvec_to_matrix(cam.rotation_axisangle))
    c2w[:3, 3] = cam.translation
    K = np.array([[cam.focal_length[0] * cam.width, 0.0, cam.principal_point[0] * cam.width],
                  [0.0, cam.focal_length[1] * cam.height, cam.principal_point[1] * cam.height],
                  [0.0, 0.0, 1.0]])  # normalised -> pixels, as CameraData.intrinsic_matrix
    dist = np.array([cam.radial[0], cam.radial[1], 0.0, 0.0, cam.radial[2]])  # OpenCV order k1 k2 p1 p2 k3
    return to_camera(cam.name, K, invert_rigid(c2w), cam.width, cam.height, units="m", pixel_centre="half",
                     distortion=dist if np.any(dist != 0) else None)


def camera_to_actorshq(camera: Camera, drop_distortion: bool = False) -> ActorsHQCamera:
    """The ``calibration.csv`` row of a deliffas Camera.

    Raises:
        LossyConversionError: tangential distortion (p1, p2), which has no column.
        ValueError: a K with skew (the CSV has none).
    """
    camera = require_distortion_fits(camera, "ActorsHQ calibration.csv", ("k1", "k2", "k3"), drop_distortion)
    K, E, dist = from_camera(camera, units="m", pixel_centre="half")
    if abs(K[0, 1]) > 1e-12:
        raise ValueError(f"camera {camera.name}: K has skew {K[0, 1]:g}; ActorsHQ's calibration.csv cannot hold it")
    c2w = invert_rigid(E)
    w, h = camera.width, camera.height
    return ActorsHQCamera(camera.name, w, h, matrix_to_rotvec(c2w[:3, :3]), c2w[:3, 3].copy(),
                          np.array([K[0, 0] / w, K[1, 1] / h]), np.array([K[0, 2] / w, K[1, 2] / h]),
                          np.array([dist[0], dist[1], dist[4]]))


def actorshq_rgb_path(root: PathLike, camera: str, frame: int) -> Path:
    """``root/rgbs/<camera>/<camera>_rgb<frame:06d>.jpg``."""
    return Path(root) / "rgbs" / camera / f"{camera}_rgb{int(frame):06d}.jpg"


def actorshq_mask_path(root: PathLike, camera: str, frame: int) -> Path:
    """``root/masks/<camera>/<camera>_mask<frame:06d>.png``."""
    return Path(root) / "masks" / camera / f"{camera}_mask{int(frame):06d}.png"


# ----------------------------------------------------------------------------------- capture format
def _read_cameras(path: Path, size: tuple[int, int] | None) -> list[Camera]:
    csv_path = in_folder(path, "calibration.csv")
    return converted(csv_path, read_actorshq_calibration(csv_path), lambda c: actorshq_to_camera(c, csv_path))


FORMAT = CaptureFormat(
    "actorshq", "ActorsHQ calibration.csv", camera_path="calibration.csv", distortion=("k1", "k2", "k3"),
    stores_size=True, detect_cameras=file_detector("calibration.csv", suffixes=(".csv",)),
    read_cameras=_read_cameras,
    write_cameras=lambda cameras, out, options: write_actorshq_calibration(
        out, [camera_to_actorshq(c, options.drop_distortion) for c in cameras]))
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
