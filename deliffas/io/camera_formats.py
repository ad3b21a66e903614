"""One entry point to read and write cameras in every supported capture format, as deliffas ``Camera`` lists.

``read_cameras(path, fmt="auto")`` detects the format from the path (``detect_camera_format``) and
returns cameras in the deliffas convention (mm, world -> camera, OpenCV axes, pixel centres at +0.5,
OpenCV distortion in ``Camera.extra["distortion"]``); ``write_cameras(cameras, out, fmt)`` writes them.
Each format module converts at its own boundary through ``deliffas.io.camera_conventions``; this
module only dispatches. It is what ``deliffas cameras SRC OUT --to FMT [--from FMT]`` calls.

| fmt | path read / written | image size from |
|---|---|---|
| dynacap | ``*.calibration`` | the file |
| colmap | a model folder (``cameras.bin``/``.txt``) | the file |
| easymocap | a folder with ``intri.yml`` + ``extri.yml`` (or either file) | ``W_``/``H_``, else ``size=`` |
| zju | ``annots.npy`` (or its folder) | ``size=`` (never stored) |
| nerfstudio | ``transforms.json`` (or its folder) | the file |
| thuman4 | ``calibration.json`` / ``calibration_full.json`` (or its folder) | the file |
| actorshq | ``calibration.csv`` (or its folder) | the file |
| dna | ``*.smc`` | its images/masks, else ``size=`` |

Writers refuse (``LossyConversionError``) a camera whose lens distortion the target cannot hold
(dynacap, colmap and thuman4 hold none; actorshq only radial k1, k2, k3) unless ``drop_distortion=True``,
which logs a warning per camera.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, Sequence

from deliffas.io.formats.actorshq import actorshq_to_camera, camera_to_actorshq, read_actorshq_calibration, write_actorshq_calibration
from deliffas.io.formats.dynacap.calibration import read_calibration, write_calibration
from deliffas.io.camera_conventions import require_distortion_fits
from deliffas.io.cameras import Camera
from deliffas.io.infra.reader_checks import naming_file, read_json
from deliffas.io.formats.colmap import cameras_from_colmap, cameras_to_colmap
from deliffas.io.formats.dna_rendering import cameras_to_smc, smc_to_cameras, write_smc
from deliffas.io.formats.easymocap import camera_to_easymocap, easymocap_to_camera, read_easymocap_cameras, write_easymocap_cameras
from deliffas.io.formats.nerfstudio import camera_to_nerfstudio, nerfstudio_to_camera, read_transforms, write_transforms
from deliffas.io.formats.thuman4 import (camera_to_thuman4, read_thuman4_calibration, thuman4_calibration_path, thuman4_to_camera,
                                 write_thuman4_calibration)
from deliffas.io.formats.zju_mocap import cameras_to_zju, read_zju_annots, write_zju_annots, zju_to_cameras

__all__ = ["CAMERA_FORMATS", "CameraFormat", "detect_camera_format", "read_cameras", "write_cameras"]

CameraFormat = Literal["dynacap", "colmap", "easymocap", "zju", "nerfstudio", "thuman4", "actorshq", "dna"]
CAMERA_FORMATS: tuple[str, ...] = ("dynacap", "colmap", "easymocap", "zju", "nerfstudio", "thuman4", "actorshq", "dna")
"""Every ``fmt`` accepted by ``read_cameras`` and ``write_cameras``."""

PathLike = str | os.PathLike

_BY_NAME = {
    "annots.npy": "zju", "intri.yml": "easymocap", "extri.yml": "easymocap", "transforms.json": "nerfstudio",
    "calibration.json": "thuman4", "calibration_full.json": "thuman4", "calibration.csv": "actorshq",
    "cameras.bin": "colmap", "cameras.txt": "colmap",
}
_BY_SUFFIX = {".calibration": "dynacap", ".smc": "dna", ".npy": "zju", ".yml": "easymocap", ".csv": "actorshq"}


def detect_camera_format(path: PathLike) -> str:
    """The camera format of ``path`` (a file, or a folder holding one of the known file names).

    Raises:
        ValueError: nothing recognisable, naming what was looked for.
    """
    p = Path(path)
    if p.is_dir():
        for name, fmt in _BY_NAME.items():
            if (p / name).is_file():
                return fmt
        raise ValueError(f"{p}: no camera file found (looked for {', '.join(_BY_NAME)}); pass fmt=")
    if p.name in _BY_NAME:
        return _BY_NAME[p.name]
    if p.suffix in _BY_SUFFIX:
        return _BY_SUFFIX[p.suffix]
    if p.suffix == ".json":
        data = read_json(p)
        return "nerfstudio" if isinstance(data, dict) and "frames" in data else "thuman4"
    raise ValueError(f"{p}: cannot tell the camera format from the name; pass fmt= (one of {', '.join(CAMERA_FORMATS)})")


def _need_size(fmt: str, size: tuple[int, int] | None) -> tuple[int, int]:
    if size is None:
        raise ValueError(f"{fmt} cameras: the file stores no image size; pass size=(width, height)")
    w, h = (int(v) for v in size)
    if w <= 0 or h <= 0:
        raise ValueError(f"{fmt} cameras: size must be positive, got {size}")
    return w, h


def read_cameras(path: PathLike, fmt: str = "auto", size: tuple[int, int] | None = None) -> list[Camera]:
    """Read the cameras of ``path`` as deliffas Cameras.

    Args:
        fmt: one of ``CAMERA_FORMATS``, or "auto" (``detect_camera_format``).
        size: (width, height) for formats or files that store no image size (see the module table);
            ignored where the file has it.

    Raises:
        CaptureFormatError: a malformed file (each reader names the file and key).
        ValueError: an unknown format, or a required ``size`` missing.
    """
    fmt = detect_camera_format(path) if fmt == "auto" else fmt
    p = Path(path)
    if fmt == "dynacap":
        return read_calibration(p)
    if fmt == "colmap":
        return cameras_from_colmap(p if p.is_dir() else p.parent)
    if fmt == "easymocap":
        intri = p / "intri.yml" if p.is_dir() else p.with_name("intri.yml")
        return _converted(intri, read_easymocap_cameras(intri), lambda c: easymocap_to_camera(c, size))
    if fmt == "zju":
        annots = read_zju_annots(p)
        with naming_file(p / "annots.npy" if p.is_dir() else p, "cams"):
            return zju_to_cameras(annots, _need_size("zju", size))
    if fmt == "nerfstudio":
        return _converted(p / "transforms.json" if p.is_dir() else p, read_transforms(p), nerfstudio_to_camera)
    if fmt == "thuman4":
        return _converted(thuman4_calibration_path(p), read_thuman4_calibration(p), thuman4_to_camera)
    if fmt == "actorshq":
        csv_path = p / "calibration.csv" if p.is_dir() else p
        return _converted(csv_path, read_actorshq_calibration(csv_path), lambda c: actorshq_to_camera(c, csv_path))
    if fmt == "dna":
        return smc_to_cameras(p, size)
    raise ValueError(f"unknown camera format {fmt!r}; expected one of {', '.join(CAMERA_FORMATS)} or 'auto'")


def _converted(path: Path, records: Sequence, convert) -> list[Camera]:
    """``convert`` of each record, a refused value (singular K, a translation that overflows in mm) named
    with the file and the camera."""
    out = []
    for r in records:
        with naming_file(path, f"camera {r.name}"):
            out.append(convert(r))
    return out


def write_cameras(cameras: Sequence[Camera], out: PathLike, fmt: str, drop_distortion: bool = False,
                  text: bool = False) -> Path:
    """Write ``cameras`` in ``fmt``; returns the file (or folder, for colmap/easymocap) written.

    ``out`` is the file to write, or a folder that gets the format's usual file name (``annots.npy``,
    ``transforms.json``, ``calibration.json``, ``calibration.csv``); colmap and easymocap write into
    the folder ``out``; dynacap and dna write the file ``out``. ``text``: COLMAP's .txt model instead
    of .bin.

    Raises:
        LossyConversionError: distortion the format cannot hold (unless ``drop_distortion``).
        ValueError: an unknown format, or a camera the format cannot represent (e.g. skew).
    """
    out_p = Path(out)
    cameras = list(cameras)
    if not cameras:
        raise ValueError("write_cameras: no cameras to write")
    if fmt == "dynacap":
        cams = [require_distortion_fits(c, "DynaCap .calibration", (), drop_distortion, radial_fits=True) for c in cameras]
        out_p.parent.mkdir(parents=True, exist_ok=True)
        write_calibration(out_p, cams)
        return out_p
    if fmt == "colmap":
        cams = [require_distortion_fits(c, "COLMAP PINHOLE", (), drop_distortion) for c in cameras]
        cameras_to_colmap(cams, out_p, text)
        return out_p
    if fmt == "easymocap":
        write_easymocap_cameras(out_p, [camera_to_easymocap(c, drop_distortion) for c in cameras])
        return out_p
    if fmt == "zju":
        return write_zju_annots(out_p, cameras_to_zju(cameras, drop_distortion=drop_distortion))
    if fmt == "nerfstudio":
        return write_transforms(out_p, [camera_to_nerfstudio(c, drop_distortion=drop_distortion) for c in cameras])
    if fmt == "thuman4":
        return write_thuman4_calibration(out_p, [camera_to_thuman4(c, drop_distortion) for c in cameras])
    if fmt == "actorshq":
        return write_actorshq_calibration(out_p, [camera_to_actorshq(c, drop_distortion) for c in cameras])
    if fmt == "dna":
        write_smc(out_p, cameras_to_smc(cameras, drop_distortion))
        return out_p
    raise ValueError(f"unknown camera format {fmt!r}; expected one of {', '.join(CAMERA_FORMATS)}")
