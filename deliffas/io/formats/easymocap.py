"""EasyMocap cameras (``intri.yml`` / ``extri.yml``) and SMPL results (``output*/smpl/<frame>.json``) as plain records.

Conventions, worked out from EasyMocap itself (zju3dv/EasyMocap @d2a0a2d):

- Files: OpenCV FileStorage YAML (read with PyYAML's pure-Python loader: OpenCV's own parser hangs on
  some damaged files). ``easymocap/mytools/camera_utils.py`` (``read_camera``,
  ``write_camera``) reads ``names`` (a list, in both files), per camera ``K_<cam>`` (3, 3) and
  ``dist_<cam>`` (1, 5) (``D_<cam>`` as a fallback), optional ``H_<cam>``/``W_<cam>`` image size in
  ``intri.yml``; ``R_<cam>`` (3, 1) Rodrigues vector, ``Rot_<cam>`` (3, 3) matrix and ``T_<cam>``
  (3, 1) in ``extri.yml``. EasyMocap's reader uses ``R_`` (``cv2.Rodrigues``) and ignores ``Rot_``;
  so do we, and a ``Rot_`` that disagrees with it is an error. A camera name that is a number may be
  stored unquoted (EasyMocap turns it back into ``str(int(...))``; so do we).
- Pose: world -> camera, x_cam = R X + T (``RT = hstack(R, T)``, ``P = K RT``), OpenCV camera axes.
- Units: metres (the calibration tutorial ``apps/calibration/Readme.md`` measures the chessboard
  with ``--grid 0.1``, 10 cm squares). deliffas multiplies T by 1000.
- Pixels: OpenCV (``cv2.undistort``/``cv2.projectPoints`` on these K), i.e. pixel centres on integer
  coordinates: cx_deliffas = cx + 0.5 (``camera_conventions.to_camera``).
- Distortion: OpenCV (k1, k2, p1, p2, k3), kept in ``Camera.extra["distortion"]``.
- SMPL: ``doc/02_output.md``: a list (or ``{"annots": [...]}``) of people, each ``id``, ``Rh``
  (1, 3) axis-angle global rotation, ``Th`` (1, 3) metres, ``poses`` (1, 72/78/87) with the first three
  zero, ``shapes`` (1, 10), optional ``expression``; vertices = R(Rh) X(poses, shapes) + Th.
  Read as records only; file ``<frame:06d>.json`` is frame ``frame``.

Our writer puts full float64 precision in the files (EasyMocap's own writes six decimals) and the
header EasyMocap writes (``%YAML:1.0``), which every OpenCV version parses.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.camera_conventions import from_camera, require_distortion_fits, to_camera
from deliffas.io.infra.reader_checks import (CaptureFormatError, read_json, require_array, require_rotation, require_rows,
                                        require_size, write_json_atomic)
from deliffas.io.infra.files import durable_replace, temp_path
from deliffas.io.format_registry import CaptureFormat
from deliffas.io.formats.camera_files import converted, file_detector, need_size

__all__ = [
    "EasyMocapCamera",
    "EasyMocapSmpl",
    "read_easymocap_cameras",
    "write_easymocap_cameras",
    "read_easymocap_smpl",
    "write_easymocap_smpl",
    "easymocap_to_camera",
    "camera_to_easymocap",
    "RVEC_TOL",
]

PathLike = str | os.PathLike

RVEC_TOL = 1e-5
"""How far ``Rot_<cam>`` may differ from ``Rodrigues(R_<cam>)`` (max abs): EasyMocap writes both
with six decimals."""


@dataclass(frozen=True)
class EasyMocapCamera:
    """One camera of ``intri.yml`` + ``extri.yml``, in the files' own conventions.

    Attributes:
        name: the entry of ``names`` (``K_<name>`` etc.).
        K: (3, 3) float64 intrinsics, pixels, OpenCV pixel centres (integers).
        dist: (5,) float64 OpenCV distortion (k1, k2, p1, p2, k3).
        R: (3, 3) float64 world -> camera rotation.
        T: (3,) float64 world -> camera translation, metres.
        width: ``W_<name>`` in pixels, or None when the file has none.
        height: ``H_<name>`` in pixels, or None when the file has none.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    T: np.ndarray
    width: int | None = None
    height: int | None = None


@dataclass(frozen=True)
class EasyMocapSmpl:
    """One person's SMPL/SMPL-H/SMPL-X parameters in EasyMocap's Rh/Th form (no SMPL maths here).

    Attributes:
        id: the person id (0 for single-person files and ZJU-MoCap).
        Rh: (1, 3) float64 global rotation, axis-angle radians.
        Th: (1, 3) float64 global translation, metres.
        poses: (1, P) float64 pose parameters (P = 72, 78 or 87; the first three are zero).
        shapes: (1, S) float64 shape coefficients.
        expression: (1, E) float64 SMPL-X expression, or None.
    """

    id: int
    Rh: np.ndarray
    Th: np.ndarray
    poses: np.ndarray
    shapes: np.ndarray
    expression: np.ndarray | None = None


@functools.lru_cache(maxsize=1)
def _yaml_loader():
    """PyYAML's pure-Python safe loader, taught OpenCV's ``!!opencv-matrix`` tag (a plain mapping) and floats
    without a dot such as ``1e-05`` (YAML 1.1 reads them as text; OpenCV and Python's repr write them)."""
    import re

    import yaml

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", lambda loader, node: loader.construct_mapping(node))
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9]+[eE][-+]?[0-9]+$"),
                                 list("-+0123456789"))
    return Loader


def _open_storage(path: Path) -> dict:
    """The top-level mapping of an OpenCV FileStorage YAML file.

    Parsed with PyYAML's pure-Python loader, not ``cv2.FileStorage``: OpenCV's parser loops forever on
    some damaged files (an indented mapping, ``---``, an indented list: found by fuzzing) and sized
    matrix buffers from unchecked ``rows``/``cols`` (the process crashed).
    """
    import yaml

    if not path.is_file():
        raise CaptureFormatError(path, "file", "not found")
    raw = path.read_bytes()
    if not raw:
        raise CaptureFormatError(path, "YAML", "expected an OpenCV FileStorage file, got an empty file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise CaptureFormatError(path, "YAML", "expected an OpenCV FileStorage file, got non-UTF-8 bytes") from None
    if text.startswith("%YAML:"):  # OpenCV's directive, which is not YAML's "%YAML 1.x"
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        doc = yaml.load(text, Loader=_yaml_loader())
    except (yaml.YAMLError, RecursionError, ValueError, TypeError) as err:  # TypeError/ValueError: e.g. an
        detail = " ".join(str(err).split())  # unhashable key, a date YAML cannot build
        raise CaptureFormatError(path, "YAML", f"expected an OpenCV FileStorage file; YAML: {detail[:200]}") from None
    if not isinstance(doc, dict):
        raise CaptureFormatError(path, "YAML", "expected keys (names, K_<cam>, ...) at the top level")
    return doc


_MAX_MATRIX = 4096
"""Most numbers a matrix of these files may hold (the largest, K or Rot_, holds 9)."""


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _mat(doc: dict, path: Path, key: str, shape: tuple[int, ...], required: bool = True) -> np.ndarray | None:
    """The !!opencv-matrix ``key`` (rows, cols, data), checked before any array is made."""
    node = doc.get(key)
    if node is None:
        if required:
            raise CaptureFormatError(path, key, f"expected an !!opencv-matrix of shape {shape}, got no such key")
        return None
    if not isinstance(node, dict):
        raise CaptureFormatError(path, key, "expected an !!opencv-matrix (rows, cols, dt, data)")
    r, c, data = node.get("rows"), node.get("cols"), node.get("data")
    if not (type(r) is int and type(c) is int and isinstance(data, list)):
        raise CaptureFormatError(path, key, "expected an !!opencv-matrix with integer rows and cols and a data list")
    if not (r > 0 and c > 0 and r * c == len(data) <= _MAX_MATRIX):
        raise CaptureFormatError(path, key, f"expected rows x cols = the {len(data)} numbers of data, got {r} x {c}")
    for i, v in enumerate(data):
        if not _number(v):
            raise CaptureFormatError(path, f"{key}/data[{i}]", f"expected a number, got {v!r}"[:120])
    return require_array(path, key, np.reshape(data, (r, c)), shape, reshape=True)


def _names(doc: dict, path: Path) -> list[str]:
    node = doc.get("names")
    if not isinstance(node, list):
        raise CaptureFormatError(path, "names", "expected a list of camera names")
    out = []
    for i, item in enumerate(node):
        if isinstance(item, str):
            out.append(item)
        elif isinstance(item, int) and not isinstance(item, bool):
            out.append(str(item))  # EasyMocap: unquoted numbers are camera names too (any size: YAML ints are exact)
        elif _number(item) and float(item).is_integer():
            out.append(str(int(item)))
        else:
            raise CaptureFormatError(path, f"names[{i}]", "expected a camera name (string or integer)")
    if not out:
        raise CaptureFormatError(path, "names", "expected at least one camera name, got an empty list")
    if len(set(out)) != len(out):
        raise CaptureFormatError(path, "names", "expected distinct camera names, got duplicates")
    return out


def _int(doc: dict, path: Path, key: str) -> float | None:
    node = doc.get(key)
    if node is None:
        return None
    if not _number(node):
        raise CaptureFormatError(path, key, "expected an integer image size")
    return node


def read_easymocap_cameras(intri: PathLike, extri: PathLike | None = None) -> list[EasyMocapCamera]:
    """Read EasyMocap ``intri.yml`` and ``extri.yml`` (``extri`` defaults to the sibling of ``intri``;
    ``intri`` may also be their folder). Cameras come in the order of ``intri.yml``'s ``names``.

    Raises:
        CaptureFormatError: a missing file or key, a truncated or unparsable file, a wrong shape, NaN/inf,
            a non-rotation, or ``R_``/``Rot_`` that disagree.
    """
    import cv2

    intri_p = Path(intri)
    if intri_p.is_dir():
        intri_p = intri_p / "intri.yml"
    extri_p = Path(extri) if extri is not None else intri_p.with_name("extri.yml")
    fi, fe = _open_storage(intri_p), _open_storage(extri_p)
    names = _names(fi, intri_p)
    missing = sorted(set(names) - set(_names(fe, extri_p)))
    if missing:
        raise CaptureFormatError(extri_p, "names", f"expected every camera of {intri_p.name}, missing {missing[:5]}")
    cams = []
    for n in names:
        K = _mat(fi, intri_p, f"K_{n}", (3, 3))
        dist = _mat(fi, intri_p, f"dist_{n}", (-1, -1), required=False)
        key = f"dist_{n}"
        if dist is None:
            dist, key = _mat(fi, intri_p, f"D_{n}", (-1, -1)), f"D_{n}"
        if dist.size not in (4, 5):
            raise CaptureFormatError(intri_p, key, f"expected 4 or 5 OpenCV distortion coefficients, got {dist.size}")
        d5 = np.zeros(5)
        d5[: dist.size] = dist.ravel()
        w, h = _int(fi, intri_p, f"W_{n}"), _int(fi, intri_p, f"H_{n}")
        size = (None, None)
        if w is not None and h is not None and (w, h) != (-1, -1):  # EasyMocap writes -1 for "unknown"
            size = require_size(intri_p, f"W_{n}/H_{n}", w, h)
        rvec = _mat(fe, extri_p, f"R_{n}", (3, 1), required=False)
        rot = _mat(fe, extri_p, f"Rot_{n}", (3, 3), required=False)
        if rvec is None and rot is None:
            raise CaptureFormatError(extri_p, f"R_{n}", "expected a Rodrigues vector R_ (or a matrix Rot_), got neither")
        if rvec is not None:
            R = require_rotation(extri_p, f"R_{n}", cv2.Rodrigues(rvec)[0])
            if rot is not None and np.abs(rot - R).max() > RVEC_TOL:
                raise CaptureFormatError(extri_p, f"Rot_{n}", f"expected Rodrigues(R_{n}) within {RVEC_TOL:g}, "
                                                              f"got max difference {np.abs(rot - R).max():.3g}")
        else:
            R = require_rotation(extri_p, f"Rot_{n}", rot)
        T = _mat(fe, extri_p, f"T_{n}", (3, 1)).ravel()
        cams.append(EasyMocapCamera(n, K, d5, R, T, *size))
    return cams


def _yaml_matrix(key: str, m: np.ndarray) -> str:
    m = np.asarray(m, np.float64)
    m = m.reshape(m.shape[0], -1)
    data = ", ".join(repr(float(v)) for v in m.ravel())  # repr: the shortest text that reads back bit-exact
    return f"{key}: !!opencv-matrix\n  rows: {m.shape[0]}\n  cols: {m.shape[1]}\n  dt: d\n  data: [{data}]\n"


def _yaml_names(names: Sequence[str]) -> str:
    for n in names:
        if not n or any(c in n for c in "\"\\\n:#") or n != n.strip():
            raise ValueError(f"camera name {n!r} cannot be an EasyMocap key (K_<name>)")
    return "names:\n" + "".join(f'  - "{n}"\n' for n in names)


def _write_yaml(path: Path, body: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
        fh.write("%YAML:1.0\n---\n" + body)
    durable_replace(tmp, path)


def write_easymocap_cameras(out_dir: PathLike, cameras: Sequence[EasyMocapCamera]) -> tuple[Path, Path]:
    """Write ``out_dir/intri.yml`` and ``out_dir/extri.yml`` (atomically each); returns their paths.

    Both ``R_`` (Rodrigues) and ``Rot_`` are written, as EasyMocap does; ``H_``/``W_`` when known.
    """
    import cv2

    out = Path(out_dir)
    names = [c.name for c in cameras]
    intri, extri = _yaml_names(names), _yaml_names(names)
    for c in cameras:
        intri += _yaml_matrix(f"K_{c.name}", c.K) + _yaml_matrix(f"dist_{c.name}", np.reshape(c.dist, (1, -1)))
        if c.width is not None and c.height is not None:
            intri += f"H_{c.name}: {int(c.height)}\nW_{c.name}: {int(c.width)}\n"
        rvec = cv2.Rodrigues(np.asarray(c.R, np.float64))[0]
        extri += (_yaml_matrix(f"R_{c.name}", rvec) + _yaml_matrix(f"Rot_{c.name}", c.R)
                  + _yaml_matrix(f"T_{c.name}", np.reshape(c.T, (3, 1))))
    _write_yaml(out / "intri.yml", intri)
    _write_yaml(out / "extri.yml", extri)
    return out / "intri.yml", out / "extri.yml"


def easymocap_to_camera(cam: EasyMocapCamera, size: tuple[int, int] | None = None) -> Camera:
    """The deliffas Camera (mm, +0.5 pixel centres, distortion in ``extra``).

    Args:
        size: (width, height) used when the file has no ``W_``/``H_``.

    Raises:
        ValueError: no image size in the file and none given.
    """
    if cam.width is not None and cam.height is not None:
        w, h = cam.width, cam.height
    elif size is not None:
        w, h = size
    else:
        raise ValueError(f"EasyMocap camera {cam.name}: intri.yml has no W_/H_; pass --size WxH")
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = cam.R, cam.T
    return to_camera(cam.name, cam.K, E, w, h, units="m", pixel_centre="integer", distortion=cam.dist)


def camera_to_easymocap(camera: Camera, drop_distortion: bool = False) -> EasyMocapCamera:
    """The EasyMocap record of a deliffas Camera (metres, OpenCV pixel centres, with its size)."""
    camera = require_distortion_fits(camera, "EasyMocap", ("k1", "k2", "p1", "p2", "k3"), drop_distortion)
    K, E, dist = from_camera(camera, units="m", pixel_centre="integer")
    return EasyMocapCamera(camera.name, K, dist, E[:3, :3].copy(), E[:3, 3].copy(), camera.width, camera.height)


def read_easymocap_smpl(path: PathLike) -> list[EasyMocapSmpl]:
    """Read ``output*/smpl/<frame>.json``: a list of people (or ``{"annots": [...]}``).

    Raises:
        CaptureFormatError: unreadable JSON, a missing key, a wrong shape or NaN/inf.
    """
    p = Path(path)
    data = read_json(p)
    if isinstance(data, dict) and "annots" in data:
        data = data["annots"]
    if not isinstance(data, list):
        raise CaptureFormatError(p, "(top level)", f"expected a list of people, got {type(data).__name__}")
    out = []
    for i, person in enumerate(data):
        if not isinstance(person, dict):
            raise CaptureFormatError(p, f"[{i}]", "expected an object with id, Rh, Th, poses, shapes")
        for key in ("Rh", "Th", "poses", "shapes"):
            if key not in person:
                raise CaptureFormatError(p, f"[{i}].{key}", "missing")
        Rh = require_array(p, f"[{i}].Rh", person["Rh"], (1, 3), reshape=True)
        Th = require_array(p, f"[{i}].Th", person["Th"], (1, 3), reshape=True)
        poses = require_rows(p, f"[{i}].poses", person["poses"], rows=1)
        shapes = require_rows(p, f"[{i}].shapes", person["shapes"], rows=1)
        expr = person.get("expression")
        expr = None if expr is None else require_rows(p, f"[{i}].expression", expr, rows=1)
        pid = person.get("id", i)
        if isinstance(pid, bool) or not (isinstance(pid, int) or (isinstance(pid, float) and pid.is_integer())):
            raise CaptureFormatError(p, f"[{i}].id", f"expected an integer person id, got {pid!r}"[:120])
        out.append(EasyMocapSmpl(int(pid), Rh, Th, poses, shapes, expr))
    return out


def write_easymocap_smpl(path: PathLike, people: Sequence[EasyMocapSmpl]) -> None:
    """Write one ``smpl/<frame>.json`` (a list of people, full precision, atomically)."""
    rows = []
    for s in people:
        row = {"id": int(s.id), "Rh": np.asarray(s.Rh).tolist(), "Th": np.asarray(s.Th).tolist(),
               "poses": np.asarray(s.poses).tolist(), "shapes": np.asarray(s.shapes).tolist()}
        if s.expression is not None:
            row["expression"] = np.asarray(s.expression).tolist()
        rows.append(row)
    write_json_atomic(path, rows)


# ----------------------------------------------------------------------------------- capture format
def _read_cameras(path: Path, size: tuple[int, int] | None) -> list[Camera]:
    intri = path / "intri.yml" if path.is_dir() else path.with_name("intri.yml")
    def convert(c: EasyMocapCamera) -> Camera:  # no W_/H_: --size, else the camera's first image
        missing = c.width is None or c.height is None
        return easymocap_to_camera(c, need_size("easymocap", size, intri.parent / "images" / c.name, c.name)
                                   if missing else None)
    return converted(intri, read_easymocap_cameras(intri), convert)


FORMAT = CaptureFormat(
    "easymocap", "EasyMocap intri.yml / extri.yml", camera_path=".", distortion=("k1", "k2", "p1", "p2", "k3"),
    stores_size=False, detect_cameras=file_detector("intri.yml", "extri.yml", suffixes=(".yml",)),
    read_cameras=_read_cameras,
    write_cameras=lambda cameras, out, options: write_easymocap_cameras(
        out, [camera_to_easymocap(c, options.drop_distortion) for c in cameras])[0].parent)
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
