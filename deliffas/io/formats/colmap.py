"""COLMAP import/export of DynaCap cameras (PINHOLE models, poses, an empty point cloud).

Pixel conventions, worked out:

- DynaCap/deliffas (docs/conventions.md): pixel (col, row) is sampled at the continuous image point
  (col + 0.5, row + 0.5) with K, i.e. integer coordinates lie on pixel *corners* and the image spans
  [0, W] x [0, H].
- COLMAP: "the upper left image corner has coordinate (0, 0) and the center of the upper left most
  pixel has coordinate (0.5, 0.5)" (COLMAP documentation, Database Format / Keypoints); its camera
  models project x_img = f x/z + c in that continuous system, and ``Camera.create`` puts the
  default principal point at (W/2, H/2), the image centre in that system.
- Hence the two agree: fx, fy, cx, cy are copied **unchanged**. The half-pixel shift exists only
  against OpenCV, whose pixel centres sit on integer coordinates: c_opencv = c_dynacap - 0.5.

Extrinsics: COLMAP's ``cam_from_world`` is the same world -> camera map as ``Camera.world_to_cam``
(x_cam = R X + t, camera looking along +z, x right, y down); translations keep the calibration's
millimetres (COLMAP is scale-free). Camera and image ids are 1-based calibration indices; image
names are the calibration names.

pycolmap is imported here only, at call time (docs/conventions.md), and only to write: models are read by
``deliffas.io.formats.colmap_model``, which checks every count of a binary model before trusting it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.camera_conventions import require_distortion_fits
from deliffas.io.infra.reader_checks import CaptureFormatError, naming_file
from deliffas.io.formats.colmap_model import read_colmap_model
from deliffas.io.format_registry import CameraWriteOptions, CaptureFormat
from deliffas.io.formats.camera_files import file_detector
from deliffas.optional import import_optional

__all__ = [
    "cameras_to_colmap",
    "cameras_from_colmap",
    "opencv_principal_point",
]


def _pycolmap():
    return import_optional("pycolmap", "deliffas cameras --to-colmap/--from-colmap needs the 'pycolmap' package")


def opencv_principal_point(camera: Camera) -> tuple[float, float]:
    """(cx, cy) in OpenCV's convention (pixel centres on integers): DynaCap/COLMAP values minus 0.5."""
    return float(camera.K[0, 2] - 0.5), float(camera.K[1, 2] - 0.5)


def cameras_to_colmap(cameras: Sequence[Camera], out_dir: str | os.PathLike, text: bool = False) -> None:
    """Write ``cameras`` as a COLMAP sparse model (PINHOLE cameras, one image per camera, no points).

    Raises:
        ValueError: a camera with skew or a K whose last row is not (0, 0, 1) (PINHOLE cannot hold it).
    """
    pycolmap = _pycolmap()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    for i, cam in enumerate(cameras):  # a few hundred cameras at most
        K = np.asarray(cam.K, np.float64)
        if abs(K[0, 1]) > 1e-12 or np.abs(K[2] - [0, 0, 1]).max() > 1e-12 or abs(K[1, 0]) > 1e-12:
            raise ValueError(f"camera {cam.name}: K has skew or a non-(0, 0, 1) last row; PINHOLE cannot represent it")
        ccam = pycolmap.Camera(camera_id=i + 1, model="PINHOLE", width=int(cam.width), height=int(cam.height),
                               params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        rec.add_camera_with_trivial_rig(ccam)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(cam.R, np.float64)), np.asarray(cam.t, np.float64))
        img = pycolmap.Image(image_id=i + 1, name=str(cam.name), camera_id=i + 1)
        rec.add_image_with_trivial_frame(img, pose)
    if text:
        rec.write_text(str(out))
    else:
        rec.write_binary(str(out))


def cameras_from_colmap(model_dir: str | os.PathLike) -> list[Camera]:
    """Read the images of a COLMAP model as Cameras (ordered by image id), through ``read_colmap_model``.

    Only pinhole-type models without distortion are accepted (PINHOLE, SIMPLE_PINHOLE).

    Raises:
        FileNotFoundError: ``model_dir`` is not a folder.
        CaptureFormatError: a malformed model, an image with another camera model, or a camera that is not
            a valid pinhole (zero focal length), naming the file and the record.
    """
    d = Path(model_dir)
    cameras, images = read_colmap_model(d)
    ext = ".bin" if (d / "cameras.bin").is_file() else ".txt"
    out = []
    for image_id in sorted(images):
        img = images[image_id]
        cc = cameras[img.camera_id]
        p = cc.params
        if cc.model == "SIMPLE_PINHOLE":
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        elif cc.model == "PINHOLE":
            fx, fy, cx, cy = p
        else:
            raise CaptureFormatError(d / f"cameras{ext}", f"camera {cc.camera_id}",
                                     f"image {img.name} uses camera model {cc.model}; only PINHOLE/SIMPLE_PINHOLE are supported")
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        E = np.eye(4)
        E[:3, :3] = _quaternion_matrix(img.qvec)
        E[:3, 3] = img.tvec
        with naming_file(d / f"images{ext}", f"image {image_id}"):
            out.append(Camera(img.name, K, E, cc.width, cc.height))
    return out


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# ----------------------------------------------------------------------------------- capture format
def _write_cameras(cameras: Sequence[Camera], out: Path, options: CameraWriteOptions) -> Path:
    cams = [require_distortion_fits(c, "COLMAP PINHOLE", (), options.drop_distortion) for c in cameras]
    cameras_to_colmap(cams, out, options.text)
    return out


FORMAT = CaptureFormat(
    "colmap", "COLMAP sparse model", camera_path=".", distortion=(), stores_size=True,
    text_variant="the .txt model instead of .bin", shorthand_with="dynacap",
    detect_cameras=file_detector("cameras.bin", "cameras.txt"),
    read_cameras=lambda path, size: cameras_from_colmap(path if path.is_dir() else path.parent),
    write_cameras=_write_cameras)
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
