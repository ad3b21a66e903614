"""DNA-Rendering ``.smc`` files (HDF5): calibration, frame counts, JPEG images and masks, SMPL-X, read and written.

Conventions, worked out from the dataset's own reader (DNA-Rendering/DNA-Rendering @2691286:
``scripts/3DGS/SMCReader.py`` and ``scripts/3DGS/dataset_readers.py``):

- An ``.smc`` is an HDF5 file. A capture comes as a main file (images) and an ``_annots.smc``
  (calibration, masks, keypoints, SMPL-X); the groups below may sit in either, and every function here
  reads whichever groups the given file has.
- ``Camera_Parameter/<id:02d>/{K, D, RT, Color_Calibration}``: ``K`` (3, 3) pixels, ``D`` OpenCV
  (k1, k2, p1, p2, k3) ("D = cam_params['D'] # k1, k2, p1, p2, k3"), ``RT`` (4, 4) **camera-to-world**
  (``dataset_readers.py``: ``c2w = RT; w2c = inv(c2w)``), OpenCV camera axes.
- Units: **metres** (SMPL-X vertices, in metres, are rendered with these cameras); deliffas x 1000.
- Pixels: images and masks go through ``cv2.undistort(image, K, D)``: OpenCV pixel centres on integers,
  cx_deliffas = cx + 0.5.
- Images: ``<group>/<id>/color/<frame>`` (group ``Camera_5mp``, ids "0".."47", or ``Camera_12mp``,
  "48".."59"), each a 1-D uint8 array holding a JPEG (``cv2.imdecode``, BGR); the group's attributes
  ``num_device``, ``num_frame``, ``resolution``. Masks: ``Mask/<id>/mask/<frame>``, JPEG, reduced to
  one channel with the max over channels. Camera ids in image groups are not zero-padded; in
  ``Camera_Parameter`` they are (``f'{int(Camera_id):02d}'``). Frames are 0-based.
- ``SMPLx/{betas, expression, fullpose (N, 55, 3), transl (N, 3), scale}``.
- Image size: from the camera's first decoded image or mask (the ``resolution`` attribute's axis order
  is not documented), else a required ``size=``.

The writer produces the same layout (one file holding all groups), with ``Color_Calibration`` = I when
none is given (``SMCReader.get_Calibration`` reads all four keys) and a ``name`` attribute per camera
when the deliffas name is not its id. Images are stored as JPEG (quality 95) like the dataset's; tests
that need exact pixels can pass ``jpeg_quality=100`` and compare with a tolerance.
"""

from __future__ import annotations

import os
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.camera_conventions import from_camera, invert_rigid, require_distortion_fits, to_camera
from deliffas.io.infra.reader_checks import (CaptureFormatError, naming_file, require_array, require_rotation, require_rows,
                                        require_vector)
from deliffas.io.infra.files import durable_replace, temp_path
from deliffas.io.infra.hdf5_heaps import looping_global_heap
from deliffas.io.format_registry import CameraWriteOptions, CaptureFormat
from deliffas.io.formats.camera_files import file_detector

__all__ = [
    "SmcCalibration",
    "SmcSmplx",
    "SmcFile",
    "read_smc_calibration",
    "write_smc",
    "smc_to_cameras",
    "cameras_to_smc",
]

PathLike = str | os.PathLike


@dataclass(frozen=True)
class SmcCalibration:
    """One camera of ``Camera_Parameter``, in the file's conventions.

    Attributes:
        camera_id: the group key, two digits (``"05"``).
        K: (3, 3) float64 intrinsics, pixels, OpenCV pixel centres.
        D: (5,) float64 OpenCV distortion (k1, k2, p1, p2, k3).
        RT: (4, 4) float64 camera -> world, metres.
        color_calibration: (3, 3) float64 colour correction matrix (identity when absent).
        name: the camera's name (the ``name`` attribute deliffas writes, else ``camera_id``).
    """

    camera_id: str
    K: np.ndarray
    D: np.ndarray
    RT: np.ndarray
    color_calibration: np.ndarray = field(default_factory=lambda: np.eye(3))
    name: str = ""


@dataclass(frozen=True)
class SmcSmplx:
    """``SMPLx``: SMPL-X parameters per frame (no SMPL maths here).

    Attributes:
        betas: (N, B) or (1, B) float64 shape.
        expression: (N, E) float64.
        fullpose: (N, 55, 3) float64 axis-angle radians (global, 21 body, jaw, eyes, 2 x 15 hand joints).
        transl: (N, 3) float64 metres.
        scale: float, the fit's scale.
    """

    betas: np.ndarray
    expression: np.ndarray
    fullpose: np.ndarray
    transl: np.ndarray
    scale: float = 1.0


class SmcFile:
    """An open ``.smc`` file: calibration, frame counts, images and masks decoded by (camera, frame).

    Use as a context manager (``with SmcFile(path) as smc: ...``); it holds the HDF5 file open.

    Raises:
        CaptureFormatError: the file is missing, truncated or not HDF5; every method raises it too for a missing,
            mistyped (a dataset where a group belongs) or damaged entry, naming the entry.
    """

    def __init__(self, path: PathLike):
        import h5py  # h5py is a dependency; imported here to keep `import deliffas.io` light

        self.path = Path(path)
        if not self.path.is_file():
            raise CaptureFormatError(self.path, "file", "not found")
        looping = looping_global_heap(self.path)  # libhdf5 would hang reading it, not raise
        if looping is not None:
            raise CaptureFormatError(self.path, "HDF5 global heap", f"damaged: {looping}")
        try:
            self._h5 = h5py.File(self.path, "r")
        except (OSError, RuntimeError, ValueError) as err:
            raise CaptureFormatError(self.path, "HDF5", f"expected a complete HDF5 (.smc) file ({err})") from None

    def __enter__(self) -> "SmcFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._h5.close()

    @contextmanager
    def _reading(self, key: str):
        """h5py's errors on a damaged file (OSError, RuntimeError, or a KeyError for an object whose header does not
        parse) raised as ``CaptureFormatError`` naming the file and ``key``."""
        try:
            yield
        except CaptureFormatError:
            raise
        except KeyError as err:
            detail = "missing" if "doesn't exist" in str(err) else f"unreadable (damaged file?): {err}"
            raise CaptureFormatError(self.path, key, detail) from None
        except (OSError, RuntimeError, ValueError) as err:  # ValueError: e.g. a name h5py cannot decode
            raise CaptureFormatError(self.path, key, f"unreadable (damaged file?): {err}") from None

    def _node(self, key: str, kind: str | None = None):
        """The group (``kind`` "group") or dataset ("dataset") at ``key``."""
        import h5py

        with self._reading(key):
            node = self._h5[key]
        want = {"group": h5py.Group, "dataset": h5py.Dataset}.get(kind)
        if want is not None and not isinstance(node, want):
            raise CaptureFormatError(self.path, key, f"expected a {kind}, got a {type(node).__name__}")
        return node

    def _names(self, node, key: str) -> list[str]:
        """The member names of the group ``node`` at ``key``; h5py gives a name that is not UTF-8 as bytes."""
        with self._reading(key):
            names = list(node.keys())
        bad = [n for n in names if not isinstance(n, str)]
        if bad:
            raise CaptureFormatError(self.path, key, f"member name {bad[0]!r} is not UTF-8 (damaged file?)")
        return names

    def _data(self, key: str):
        node = self._node(key, "dataset")
        with self._reading(key):
            return node[()]

    def calibration(self) -> list[SmcCalibration]:
        """Every camera of ``Camera_Parameter``, ordered by id."""
        group = self._node("Camera_Parameter", "group")
        out = []
        ids = sorted(self._names(group, "Camera_Parameter"), key=lambda k: (len(k), k))
        for cid in ids:
            base = f"Camera_Parameter/{cid}"
            if not (cid.isascii() and cid.isdigit()):
                raise CaptureFormatError(self.path, base, "expected a numeric camera id (00, 01, ...)")
            cam = self._node(base, "group")
            K = require_array(self.path, f"{base}/K", self._data(f"{base}/K"), (3, 3))
            D = require_vector(self.path, f"{base}/D", self._data(f"{base}/D"))
            if D.size not in (4, 5):
                raise CaptureFormatError(self.path, f"{base}/D", f"expected 4 or 5 OpenCV coefficients, got {D.size}")
            D5 = np.zeros(5)
            D5[: D.size] = D
            RT = require_array(self.path, f"{base}/RT", self._data(f"{base}/RT"), (4, 4))
            require_rotation(self.path, f"{base}/RT", RT[:3, :3])
            if np.abs(RT[3] - [0, 0, 0, 1]).max() > 1e-9:
                raise CaptureFormatError(self.path, f"{base}/RT", "expected a last row 0 0 0 1")
            cc = np.eye(3)
            if self.has(f"{base}/Color_Calibration"):
                cc = require_array(self.path, f"{base}/Color_Calibration", self._data(f"{base}/Color_Calibration"), (3, 3))
            with self._reading(f"{base}@name"):
                name = cam.attrs.get("name", cid)
            if isinstance(name, bytes):
                try:
                    name = name.decode("utf-8")
                except UnicodeDecodeError:
                    raise CaptureFormatError(self.path, f"{base}@name", "expected a UTF-8 camera name") from None
            if not isinstance(name, str):
                raise CaptureFormatError(self.path, f"{base}@name", f"expected a camera name, got {type(name).__name__}")
            out.append(SmcCalibration(cid, K, D5, RT, cc, name))
        if not out:
            raise CaptureFormatError(self.path, "Camera_Parameter", "expected at least one camera, got none")
        return out

    def has(self, key: str) -> bool:
        """Whether the file holds the group or dataset ``key`` (e.g. ``Mask``, ``SMPLx``)."""
        with self._reading(key):
            return key in self._h5

    def frame_count(self, camera: str | int, group: str = "Camera_5mp", kind: str = "color") -> int:
        """Number of frames stored for ``camera`` (``kind`` "color" in ``group``, or "mask")."""
        key = f"Mask/{int(camera)}/mask" if kind == "mask" else f"{group}/{int(camera)}/{kind}"
        node = self._node(key, "group")
        with self._reading(key):
            return len(node)

    def _jpeg(self, key: str) -> np.ndarray:
        import cv2

        buf = np.asarray(self._data(key))
        if buf.dtype != np.uint8 or buf.ndim != 1 or buf.size == 0:
            raise CaptureFormatError(self.path, key, f"expected a 1-D uint8 JPEG buffer, got {buf.dtype} {buf.shape}")
        try:
            img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        except cv2.error:
            img = None
        if img is None:
            raise CaptureFormatError(self.path, key, "expected a decodable JPEG, got corrupt or truncated bytes")
        return img

    def image(self, camera: str | int, frame: int, group: str = "Camera_5mp") -> np.ndarray:
        """(H, W, 3) uint8 **RGB** colour image of ``camera`` at ``frame`` (the file holds BGR JPEGs)."""
        return self._jpeg(f"{group}/{int(camera)}/color/{int(frame)}")[:, :, ::-1].copy()

    def mask(self, camera: str | int, frame: int) -> np.ndarray:
        """(H, W) uint8 mask of ``camera`` at ``frame`` (max over the JPEG's channels, as SMCReader)."""
        return self._jpeg(f"Mask/{int(camera)}/mask/{int(frame)}").max(axis=2)

    def image_size(self, camera: str | int, group: str = "Camera_5mp") -> tuple[int, int] | None:
        """(width, height) of ``camera``'s first colour image or mask, or None when the file has neither."""
        for key in (f"{group}/{int(camera)}/color", f"Mask/{int(camera)}/mask"):
            if self.has(key):
                node = self._node(key, "group")
                frames = [k for k in self._names(node, key) if k.isascii() and k.isdigit()]
                if frames:
                    h, w = self._jpeg(f"{key}/{min(frames, key=int)}").shape[:2]
                    return w, h
        return None

    def smplx(self) -> SmcSmplx:
        """The ``SMPLx`` group."""
        fullpose = require_array(self.path, "SMPLx/fullpose", self._data("SMPLx/fullpose"), (-1, 55, 3))
        n = fullpose.shape[0]
        if n == 0:
            raise CaptureFormatError(self.path, "SMPLx/fullpose", "expected at least one frame, got none")
        transl = require_array(self.path, "SMPLx/transl", self._data("SMPLx/transl"), (n, 3))
        betas = require_rows(self.path, "SMPLx/betas", self._data("SMPLx/betas"))
        expr = require_rows(self.path, "SMPLx/expression", self._data("SMPLx/expression"), rows=n)
        scale = 1.0
        if self.has("SMPLx/scale"):
            scale = float(require_array(self.path, "SMPLx/scale", self._data("SMPLx/scale"), (), reshape=True))
        return SmcSmplx(betas, expr, fullpose, transl, scale)


def read_smc_calibration(path: PathLike) -> list[SmcCalibration]:
    """``Camera_Parameter`` of an ``.smc`` file (see ``SmcFile.calibration``)."""
    with SmcFile(path) as smc:
        return smc.calibration()


@contextmanager
def _open_smc(source: "PathLike | SmcFile"):
    """``source`` itself when it is an open SmcFile (left open), else the file opened for the block."""
    if isinstance(source, SmcFile):
        yield source
    else:
        with SmcFile(source) as smc:
            yield smc


def smc_to_cameras(path: "PathLike | SmcFile", size: tuple[int, int] | None = None, group: str = "Camera_5mp",
                   images: "PathLike | SmcFile | None" = None) -> list[Camera]:
    """deliffas Cameras (world -> camera, mm, +0.5 pixel centres, D in ``extra``) of an ``.smc`` file.

    Args:
        path: the file, or an open SmcFile (each open checks the whole file's heaps: a capture's parser opens
            each file once and passes it).
        size: (width, height) for cameras without an image or mask in the file.
        images: another ``.smc`` (path or open SmcFile) holding the frames the sizes come from (a capture's
            main file when ``path`` is its ``_annots.smc``); None = ``path``.

    Raises:
        ValueError: a camera without images in the file and no ``size``.
    """
    out = []
    with _open_smc(path) as smc, (_open_smc(images) if images is not None else nullcontext(smc)) as frames:
        for c in smc.calibration():
            wh = frames.image_size(c.camera_id, group) or smc.image_size(c.camera_id, group) or size
            if wh is None:
                raise ValueError(f"{smc.path}: camera {c.camera_id} has no image or mask to take its size from; pass --size WxH")
            with naming_file(smc.path, f"Camera_Parameter/{c.camera_id}"):
                out.append(to_camera(c.name or c.camera_id, c.K, invert_rigid(c.RT), wh[0], wh[1], units="m",
                                     pixel_centre="integer", distortion=c.D))
    return out


def cameras_to_smc(cameras: Sequence[Camera], drop_distortion: bool = False) -> list[SmcCalibration]:
    """``Camera_Parameter`` records of deliffas Cameras, ids "00", "01", ... in order."""
    out = []
    for i, cam in enumerate(cameras):
        cam = require_distortion_fits(cam, "DNA-Rendering .smc", ("k1", "k2", "p1", "p2", "k3"), drop_distortion)
        K, E, D = from_camera(cam, units="m", pixel_centre="integer")
        out.append(SmcCalibration(f"{i:02d}", K, D, invert_rigid(E), np.eye(3), cam.name))
    return out


def write_smc(path: PathLike, calibration: Sequence[SmcCalibration],
              images: Mapping[str, Sequence[np.ndarray]] | None = None,
              masks: Mapping[str, Sequence[np.ndarray]] | None = None,
              smplx: SmcSmplx | None = None, group: str = "Camera_5mp", jpeg_quality: int = 95) -> None:
    """Write an ``.smc`` file (atomically) in the DNA-Rendering layout.

    Args:
        calibration: cameras for ``Camera_Parameter``.
        images: camera id -> frames, each (H, W, 3) uint8 **RGB**; stored as BGR JPEGs under ``group``.
        masks: camera id -> frames, each (H, W) uint8; stored as JPEGs under ``Mask``.
        smplx: the ``SMPLx`` group, or None.
    """
    import cv2
    import h5py

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(p)

    def jpeg(img: np.ndarray) -> np.ndarray:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        if not ok:
            raise ValueError(f"{p}: JPEG encoding failed for an image of shape {img.shape}")
        return buf.ravel()

    with h5py.File(tmp, "w") as h5:
        cp = h5.create_group("Camera_Parameter")
        for c in calibration:
            g = cp.create_group(f"{int(c.camera_id):02d}")
            g["K"], g["D"], g["RT"] = np.asarray(c.K, np.float64), np.asarray(c.D, np.float64), np.asarray(c.RT, np.float64)
            g["Color_Calibration"] = np.asarray(c.color_calibration, np.float64)
            if c.name and c.name != c.camera_id:
                g.attrs["name"] = c.name
        if images:
            gi = h5.create_group(group)
            first = next(iter(images.values()))[0]
            gi.attrs["num_device"] = len(images)
            gi.attrs["num_frame"] = max(len(v) for v in images.values())
            gi.attrs["resolution"] = np.array(first.shape[:2])  # (H, W) as the arrays are; readers decode instead
            for cid, frames in images.items():
                gc = gi.create_group(f"{int(cid)}/color")
                for f, img in enumerate(frames):
                    gc[str(f)] = jpeg(np.ascontiguousarray(np.asarray(img, np.uint8)[:, :, ::-1]))
        if masks:
            gm = h5.create_group("Mask")
            for cid, frames in masks.items():
                gc = gm.create_group(f"{int(cid)}/mask")
                for f, m in enumerate(frames):
                    gc[str(f)] = jpeg(np.asarray(m, np.uint8))
        if smplx is not None:
            gs = h5.create_group("SMPLx")
            for key in ("betas", "expression", "fullpose", "transl"):
                gs[key] = np.asarray(getattr(smplx, key), np.float64)
            gs["scale"] = float(smplx.scale)
    durable_replace(tmp, p)


# ----------------------------------------------------------------------------------- capture format
def _write_cameras(cameras: Sequence[Camera], out: Path, options: CameraWriteOptions) -> Path:
    write_smc(out, cameras_to_smc(cameras, options.drop_distortion))
    return out


FORMAT = CaptureFormat(
    "dna", "DNA-Rendering .smc", camera_path="capture.smc", distortion=("k1", "k2", "p1", "p2", "k3"),
    stores_size=False, detect_cameras=file_detector(suffixes=(".smc",)),
    read_cameras=lambda path, size: smc_to_cameras(path, size), write_cameras=_write_cameras)
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
