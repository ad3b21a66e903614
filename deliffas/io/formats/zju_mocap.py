"""ZJU-MoCap ``annots.npy`` (cameras and per-frame image lists) and SMPL ``params/<i>.npy`` as plain records.

Conventions, worked out from Neural Body (zju3dv/neuralbody @3c516b9), which defines the dataset:

- ``annots.npy`` is ``np.save`` of a dict: ``cams`` = {``K``: C x (3, 3), ``D``: C x (5, 1),
  ``R``: C x (3, 3), ``T``: C x (3, 1)} and ``ims`` = a list over frames of {``ims``: C image paths
  relative to the subject folder} (``tools/custom/get_annots.py``, ``lib/datasets/light_stage/
  multi_view_dataset.py``). Other keys per frame (e.g. ``kpts2d``) are ignored.
- Units: **millimetres**. ``get_annots.py`` builds ``T`` as EasyMocap's metres ``* 1000`` and the
  dataset divides it back (``T = cams['T'][i] / 1000.``); so T is copied unchanged into deliffas.
- Pose: world -> camera (x_cam = R X + T), OpenCV camera axes (the rays of
  ``lib/utils/if_nerf/if_nerf_data_utils.py::get_rays`` are ``R^T (K^-1 (i, j, 1) - T)``).
- Pixels: ``get_rays`` casts pixel (i, j) through the integer point ``np.arange(W)``, and images and
  masks go through ``cv2.undistort(img, K, D)``: OpenCV pixel centres, cx_deliffas = cx + 0.5.
- Distortion: ``D`` is OpenCV (k1, k2, p1, p2, k3); kept in ``Camera.extra["distortion"]``.
- Image size: **not stored**; ZJU-MoCap images are 1024 x 1024 (neuralbody's ``cfg.H``/``cfg.W``), and
  converting needs ``size=``.
- SMPL: ``params/<i>.npy`` (``new_params/`` for the refitted ones) is ``np.save`` of a dict with
  ``poses`` (1, 72), ``Rh`` (1, 3), ``Th`` (1, 3) metres, ``shapes`` (1, 10): EasyMocap's Rh/Th form
  (``zju_smpl/easymocap_to_neuralbody.py``). File ``<i>`` belongs to the image named ``<i>``; for
  CoreView_313/315 the image names are 1-based (the dataset subtracts one for the frame index).
- Camera names are not in the file; the folder of each camera's first image is used (``Camera_B1``),
  else a ``camera_names`` list, which deliffas adds when it writes (neuralbody ignores unknown keys),
  else "0".."C-1" (with a warning when image folders repeat). A ``camera_names`` list that repeats a name is
  refused.

``.npy`` files holding a dict are pickles. They are read with ``deliffas.io.infra.safe_pickle``, which builds
only numpy arrays, dtypes and scalars from checked arguments (never arbitrary objects).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.camera_conventions import from_camera, require_distortion_fits, to_camera
from deliffas.io.infra.reader_checks import (CaptureFormatError, naming_file, require_array, require_rotation, require_rows,
                                             require_unique_names, require_vector)
from deliffas.io.formats.easymocap import EasyMocapSmpl
from deliffas.io.infra.files import durable_replace, temp_path
from deliffas.io.infra.safe_pickle import UnsafePickleError, load_numpy_pickle
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.formats.camera_files import file_detector, in_folder, need_size

log = logging.getLogger(__name__)

__all__ = [
    "ZjuCamera",
    "ZjuAnnots",
    "read_zju_annots",
    "write_zju_annots",
    "read_zju_params",
    "write_zju_params",
    "zju_params_path",
    "zju_to_cameras",
    "cameras_to_zju",
    "load_npy_dict",
]

PathLike = str | os.PathLike

@dataclass(frozen=True)
class ZjuCamera:
    """One camera of ``annots.npy``, in the file's conventions.

    Attributes:
        name: camera name (see the module docstring for where it comes from).
        K: (3, 3) float64 intrinsics, pixels, OpenCV pixel centres.
        D: (5,) float64 OpenCV distortion (k1, k2, p1, p2, k3).
        R: (3, 3) float64 world -> camera rotation.
        T: (3,) float64 world -> camera translation, millimetres.
    """

    name: str
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    T: np.ndarray


@dataclass(frozen=True)
class ZjuAnnots:
    """The contents of ``annots.npy``.

    Attributes:
        cameras: the C cameras, in file order.
        ims: N frames x C image paths (relative to the subject folder, '/'-separated).
    """

    cameras: tuple[ZjuCamera, ...]
    ims: tuple[tuple[str, ...], ...] = ()


def load_npy_dict(path: PathLike) -> dict:
    """The dict inside an ``np.save``-d object ``.npy`` file, unpickled with numpy types only.

    Raises:
        CaptureFormatError: missing or truncated file, not a .npy, not a dict, or a refused pickle class.
    """
    p = Path(path)
    if not p.is_file():
        raise CaptureFormatError(p, "file", "not found")
    with open(p, "rb") as fh:
        try:
            version = np.lib.format.read_magic(fh)
            header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                      else np.lib.format.read_array_header_2_0)(fh)
        except Exception as err:  # numpy's header parser raises ValueError, SyntaxError or tokenize errors on damage
            raise CaptureFormatError(p, "NPY header", f"expected a .npy file ({type(err).__name__}: {err})") from None
        shape, _, dtype = header
        if dtype != np.dtype(object) or shape != ():
            raise CaptureFormatError(p, "NPY header", f"expected a saved dict (0-d object array), got {dtype} {shape}")
        try:
            obj = load_numpy_pickle(fh.read())
        except UnsafePickleError as err:
            raise CaptureFormatError(p, "pickle", f"expected a complete pickled dict of numpy arrays ({err})") from None
    obj = obj.item() if isinstance(obj, np.ndarray) and obj.shape == () else obj
    if not isinstance(obj, dict):
        raise CaptureFormatError(p, "(top level)", f"expected a dict, got {type(obj).__name__}")
    return obj


def _save_npy_dict(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    with open(tmp, "wb") as fh:
        np.save(fh, np.array(data, dtype=object))  # ZJU's layout is a pickled dict; writing one is safe (np.save pickles object arrays)
    durable_replace(tmp, path)


def _list(p: Path, key: str, value: Any, n: int | None) -> list:
    if isinstance(value, np.ndarray) and value.ndim >= 1:
        value = list(value)
    if not isinstance(value, (list, tuple)):
        raise CaptureFormatError(p, key, f"expected a list with one entry per camera, got {type(value).__name__}")
    if n is not None and len(value) != n:
        raise CaptureFormatError(p, key, f"expected {n} entries (one per camera, as cams/K), got {len(value)}")
    return list(value)


def read_zju_annots(path: PathLike) -> ZjuAnnots:
    """Read ``annots.npy`` (a file, or the subject folder holding it).

    Raises:
        CaptureFormatError: naming ``cams/<K|D|R|T>[i]`` or ``ims[f]`` for missing keys, wrong shapes,
            NaN/inf, non-rotations, and the file for truncated pickles.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "annots.npy"
    data = load_npy_dict(p)
    cams = data.get("cams")
    if not isinstance(cams, dict):
        raise CaptureFormatError(p, "cams", "expected a dict with K, D, R, T" if cams is not None else "missing")
    for key in ("K", "D", "R", "T"):
        if key not in cams:
            raise CaptureFormatError(p, f"cams/{key}", "missing")
    Ks = _list(p, "cams/K", cams["K"], None)
    n = len(Ks)
    if n == 0:
        raise CaptureFormatError(p, "cams/K", "expected at least one camera, got none")
    Ds, Rs, Ts = (_list(p, f"cams/{k}", cams[k], n) for k in ("D", "R", "T"))
    ims_raw = data.get("ims", [])
    ims = []
    for f, entry in enumerate(_list(p, "ims", ims_raw, None)):
        paths = entry.get("ims") if isinstance(entry, dict) else None
        if paths is None:
            raise CaptureFormatError(p, f"ims[{f}].ims", "missing")
        paths = [str(x) for x in _list(p, f"ims[{f}].ims", paths, n)]
        ims.append(tuple(paths))
    names = _camera_names(p, data, ims, n)
    out = []
    for i in range(n):
        K = require_array(p, f"cams/K[{i}]", Ks[i], (3, 3), reshape=True)
        D = require_vector(p, f"cams/D[{i}]", Ds[i])  # (5, 1) or (5,)
        if D.size not in (4, 5):
            raise CaptureFormatError(p, f"cams/D[{i}]", f"expected 4 or 5 OpenCV distortion coefficients, got {D.size}")
        D5 = np.zeros(5)
        D5[: D.size] = D
        R = require_rotation(p, f"cams/R[{i}]", Rs[i])
        T = require_array(p, f"cams/T[{i}]", Ts[i], (3,), reshape=True)
        out.append(ZjuCamera(names[i], K, D5, R, T))
    return ZjuAnnots(tuple(out), tuple(ims))


def _camera_names(p: Path, data: dict, ims: list, n: int) -> list[str]:
    given = data.get("camera_names")
    if given is not None:  # deliffas' own list: a repeated name is an error, not a reason to renumber
        return require_unique_names(p, "camera_names", [str(x) for x in _list(p, "camera_names", given, n)])
    if ims:
        names = [PurePosixPath(str(x).replace("\\", "/")).parent.name for x in ims[0]]
    else:
        names = [str(i) for i in range(n)]
    if len(set(names)) != n or "" in names:
        log.warning("%s: the image folders do not name the %d cameras uniquely; cameras are named 0..%d", p, n, n - 1)
        names = [str(i) for i in range(n)]
    return names


def write_zju_annots(path: PathLike, annots: ZjuAnnots) -> Path:
    """Write ``annots.npy`` (``path`` a file, or a folder to hold it); returns the file written.

    ``K``/``R`` are (3, 3), ``D`` (5, 1) and ``T`` (3, 1) float64 as ``get_annots.py`` builds them; a
    ``camera_names`` list is added for deliffas (Neural Body reads only ``cams`` and ``ims``).
    """
    p = Path(path)
    if p.is_dir() or p.suffix != ".npy":
        p = p / "annots.npy"
    cams = {
        "K": [np.asarray(c.K, np.float64) for c in annots.cameras],
        "D": [np.asarray(c.D, np.float64).reshape(-1, 1) for c in annots.cameras],
        "R": [np.asarray(c.R, np.float64) for c in annots.cameras],
        "T": [np.asarray(c.T, np.float64).reshape(3, 1) for c in annots.cameras],
    }
    data = {"cams": cams, "ims": [{"ims": list(frame)} for frame in annots.ims],
            "camera_names": [c.name for c in annots.cameras]}
    _save_npy_dict(p, data)
    return p


def zju_to_cameras(annots: ZjuAnnots, size: tuple[int, int] | list[tuple[int, int]]) -> list[Camera]:
    """deliffas Cameras (mm kept, +0.5 pixel centres, D in ``extra``) for images of ``size`` = (width, height),
    one for every camera or a list of one per camera."""
    sizes = size if isinstance(size, list) else [size] * len(annots.cameras)
    out = []
    for c, size in zip(annots.cameras, sizes):
        E = np.eye(4)
        E[:3, :3], E[:3, 3] = c.R, c.T
        out.append(to_camera(c.name, c.K, E, size[0], size[1], units="mm", pixel_centre="integer", distortion=c.D))
    return out


def cameras_to_zju(cameras: Sequence[Camera], ims: Sequence[Sequence[str]] = (), drop_distortion: bool = False) -> ZjuAnnots:
    """The ``annots.npy`` record of deliffas Cameras (``ims``: optional N x C image paths)."""
    out = []
    for cam in cameras:
        cam = require_distortion_fits(cam, "ZJU-MoCap annots.npy", ("k1", "k2", "p1", "p2", "k3"), drop_distortion)
        K, E, dist = from_camera(cam, units="mm", pixel_centre="integer")
        out.append(ZjuCamera(cam.name, K, dist, E[:3, :3].copy(), E[:3, 3].copy()))
    return ZjuAnnots(tuple(out), tuple(tuple(str(x) for x in frame) for frame in ims))


def zju_params_path(root: PathLike, index: int, new: bool = False) -> Path:
    """``root/params/<index>.npy`` (``new_params/`` with ``new``)."""
    return Path(root) / ("new_params" if new else "params") / f"{int(index)}.npy"


def read_zju_params(path: PathLike) -> EasyMocapSmpl:
    """Read one ``params/<i>.npy`` (poses, Rh, Th in metres, shapes) as an ``EasyMocapSmpl`` record.

    Raises:
        CaptureFormatError: a missing key, a wrong shape, NaN/inf or a truncated file.
    """
    p = Path(path)
    d = load_npy_dict(p)
    for key in ("poses", "Rh", "Th", "shapes"):
        if key not in d:
            raise CaptureFormatError(p, key, "missing")
    return EasyMocapSmpl(
        0,
        require_array(p, "Rh", d["Rh"], (1, 3), reshape=True),
        require_array(p, "Th", d["Th"], (1, 3), reshape=True),
        require_rows(p, "poses", d["poses"], rows=1),
        require_rows(p, "shapes", d["shapes"], rows=1),
    )


def write_zju_params(path: PathLike, params: EasyMocapSmpl) -> None:
    """Write one ``params/<i>.npy`` dict (poses, Rh, Th, shapes), atomically."""
    _save_npy_dict(Path(path), {k: np.asarray(getattr(params, k), np.float64) for k in ("poses", "Rh", "Th", "shapes")})


# ----------------------------------------------------------------------------------- capture format
def _read_cameras(path: Path, size: tuple[int, int] | None) -> list[Camera]:
    annots = read_zju_annots(path)
    file = in_folder(path, "annots.npy")
    first = annots.ims[0] if annots.ims else ()  # each camera's first image: --size, else its size
    with naming_file(file, "cams"):
        return zju_to_cameras(annots, [need_size("zju", size, file.parent / first[i] if i < len(first) else
                                                 file.parent / c.name, c.name) for i, c in enumerate(annots.cameras)])


FORMAT = CaptureFormat(
    "zju", "ZJU-MoCap annots.npy", camera_path="annots.npy", distortion=("k1", "k2", "p1", "p2", "k3"),
    stores_size=False, detect_cameras=file_detector("annots.npy", suffixes=(".npy",)), read_cameras=_read_cameras,
    write_cameras=lambda cameras, out, options: write_zju_annots(
        out, cameras_to_zju(cameras, drop_distortion=options.drop_distortion)))
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
