"""Frame sources of the capture-dataset layouts: per-camera image/mask files and DNA-Rendering ``.smc`` files.

Each source answers ``read(frame, camera) -> (rgb (H, W, 3) uint8, mask (H, W) uint8)`` (the
``deliffas.io.formats.dynacap.frames.FrameSource`` protocol) with ``camera`` the calibration index. The picklable
specs (:class:`FileFramesSpec`, :class:`SmcFramesSpec`) travel to worker processes and ``open()``
there. A camera with lens distortion (:class:`Undistortion`) gets its image and mask undistorted at
read time with OpenCV (``initUndistortRectifyMap`` + ``remap``, new camera matrix = K, so the pinhole
camera of the ``Subject`` is the calibrated K without distortion).

Masks: ``gray`` keeps the decoded grey value (soft edges, JPEG masks); ``nonzero`` maps every
non-zero value to 255 (ZJU-MoCap stores 0/1 masks and Neural Body tests ``mask != 0``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal, Mapping

import numpy as np

from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.formats.dna_rendering import SmcFile
from deliffas.io.infra.files import durable_replace, temp_path

__all__ = ["Undistortion", "FileFramesSpec", "FileFrameSource", "SmcFramesSpec", "SmcFrameSource", "undistort_maps",
           "image_file_size", "numbered_files", "write_image_file"]

log = logging.getLogger(__name__)

MaskMode = Literal["gray", "nonzero"]


@dataclass(frozen=True)
class Undistortion:
    """The lens model images of one camera were taken with.

    Attributes:
        K: (3, 3) float64 intrinsics, pixels, **OpenCV** pixel centres (integers), for the stored image size.
        D: (5,) float64 OpenCV (k1, k2, p1, p2, k3).
    """

    K: np.ndarray
    D: np.ndarray


def undistort_maps(u: Undistortion, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) (H, W) float32 for ``cv2.remap``: the undistorted image with camera matrix K."""
    import cv2

    K = np.asarray(u.K, np.float64)
    return cv2.initUndistortRectifyMap(K, np.asarray(u.D, np.float64), None, K, (int(width), int(height)), cv2.CV_32FC1)


class _Undistorter:
    """Per camera cached remap tables; cameras without an entry pass through."""

    def __init__(self, undistort: Mapping[int, Undistortion] | None, where: str):
        self.undistort = dict(undistort or {})
        self.maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if self.undistort:
            log.debug("%s: undistorting the images and masks of cameras %s at read time", where, sorted(self.undistort))

    def __call__(self, camera: int, rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = self.undistort.get(camera)
        if u is None:
            return rgb, mask
        import cv2

        h, w = mask.shape
        if camera not in self.maps:
            self.maps[camera] = undistort_maps(u, w, h)
        mx, my = self.maps[camera]
        return (cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
                cv2.remap(mask, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))


def _read(path: Path, grey: bool) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise FileNotFoundError(f"{path}: {'mask' if grey else 'image'} not found")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: expected a readable {'mask' if grey else 'image'} file, got undecodable bytes")
    return img if grey else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_image_file(path: Path, image: np.ndarray, jpeg_quality: int = 95) -> Path:
    """Write an (H, W, 3) RGB or (H, W) grey uint8 image as ``.jpg`` (``jpeg_quality``) or ``.png``, atomically."""
    import cv2


    p = Path(path)
    img = np.ascontiguousarray(image[..., ::-1] if image.ndim == 3 else image)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if p.suffix.lower() in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(p.suffix, img, params)
    if not ok:
        raise ValueError(f"{p}: cannot encode an image of shape {image.shape} as {p.suffix}")
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(p)
    tmp.write_bytes(buf.tobytes())
    durable_replace(tmp, p)
    return p


def image_file_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file (decoded)."""
    img = _read(Path(path), grey=True)
    return int(img.shape[1]), int(img.shape[0])


def numbered_files(folder: Path, prefix: str = "", suffixes: tuple[str, ...] = (".jpg", ".png")) -> dict[int, Path]:
    """``<folder>/<prefix><number><suffix>`` files by number (empty when the folder does not exist)."""
    out = {}
    if folder.is_dir():
        for p in folder.iterdir():
            stem = p.stem[len(prefix):] if p.stem.startswith(prefix) else ""
            if p.suffix.lower() in suffixes and stem.isdigit():
                out[int(stem)] = p
    return out


@dataclass(frozen=True)
class FileFramesSpec:
    """Where the image and mask files of one sequence are (one file per camera and frame).

    Attributes:
        root: the capture folder the paths are relative to.
        images: frame -> one image path per camera (calibration order), relative to ``root``.
        masks: frame -> one mask path per camera, or None (every pixel foreground).
        mask_mode: ``gray`` (decoded value) or ``nonzero`` (non-zero -> 255).
        undistort: camera index -> its lens model, for cameras whose files are distorted.
    """

    root: Path
    images: Mapping[int, tuple[str, ...]]
    masks: Mapping[int, tuple[str, ...]] | None = None
    mask_mode: MaskMode = "gray"
    undistort: Mapping[int, Undistortion] | None = None

    def open(self) -> "FileFrameSource":
        return FileFrameSource(self)

    def image_frames(self) -> set[int]:
        """Frames that have image paths."""
        return set(int(f) for f in self.images)


class FileFrameSource:
    """Reads the files a :class:`FileFramesSpec` lists (undistorting where it says)."""

    def __init__(self, spec: FileFramesSpec):
        self.spec = spec
        self._undistort = _Undistorter(spec.undistort, str(spec.root))

    def _path(self, table: Mapping[int, tuple[str, ...]], frame: int, camera: int, what: str) -> Path:
        row = table.get(int(frame))
        if row is None:
            raise FileNotFoundError(f"{self.spec.root}: no {what} listed for frame {frame}")
        if not 0 <= camera < len(row):
            raise IndexError(f"camera {camera} outside the {len(row)} cameras of frame {frame}")
        return self.spec.root / row[camera]

    def read(self, frame: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
        p = self._path(self.spec.images, frame, camera, "image")
        rgb = _read(p, grey=False)
        if self.spec.masks is None:
            mask = np.full(rgb.shape[:2], 255, np.uint8)
        else:
            mp = self._path(self.spec.masks, frame, camera, "mask")
            mask = _read(mp, grey=True)
            if mask.shape != rgb.shape[:2]:
                raise ValueError(f"{mp}: mask is {mask.shape[1]}x{mask.shape[0]}, its image {p} "
                                 f"{rgb.shape[1]}x{rgb.shape[0]}")
            if self.spec.mask_mode == "nonzero":
                mask = np.where(mask != 0, 255, 0).astype(np.uint8)
        return self._undistort(camera, rgb, mask)

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class SmcFramesSpec:
    """The frames of a DNA-Rendering ``.smc`` file.

    Attributes:
        path: the ``.smc`` holding the colour images (and masks unless ``mask_path``).
        camera_ids: the file's camera id per calibration index (``"0"``, ``"1"``, ...).
        frames: frame numbers stored.
        group: the image group (``Camera_5mp`` / ``Camera_12mp``).
        mask_path: the ``_annots.smc`` holding ``Mask`` when it is another file, else None.
        undistort: camera index -> its lens model, for cameras whose frames are distorted.
    """

    path: Path
    camera_ids: tuple[str, ...]
    frames: tuple[int, ...]
    group: str = "Camera_5mp"
    mask_path: Path | None = None
    undistort: Mapping[int, Undistortion] | None = None
    keep_open: ClassVar[bool] = True
    """A conversion keeps one source open per worker across shards: any (frame, camera) reads at one cost, and each
    open scans the whole file's HDF5 heaps (``io.infra.hdf5_heaps``, about 0.7 s per GB)."""

    def open(self) -> "SmcFrameSource":
        return SmcFrameSource(self)

    def image_frames(self) -> set[int]:
        return set(int(f) for f in self.frames)


class SmcFrameSource:
    """Decodes the JPEG images and masks of an ``.smc`` by (frame, camera index)."""

    def __init__(self, spec: SmcFramesSpec):

        self.spec = spec
        self._smc = SmcFile(spec.path)
        self._masks = SmcFile(spec.mask_path) if spec.mask_path is not None else self._smc
        self._undistort = _Undistorter(spec.undistort, str(spec.path))

    def read(self, frame: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
        if not 0 <= camera < len(self.spec.camera_ids):
            raise IndexError(f"camera {camera} outside the {len(self.spec.camera_ids)} cameras of {self.spec.path}")
        cid = self.spec.camera_ids[camera]
        rgb = self._smc.image(cid, frame, self.spec.group)
        mask = self._masks.mask(cid, frame)
        if mask.shape != rgb.shape[:2]:
            raise CaptureFormatError(self._masks.path, f"Mask/{int(cid)}/mask/{int(frame)}",
                                     f"mask is {mask.shape[1]}x{mask.shape[0]}, its image {rgb.shape[1]}x{rgb.shape[0]}")
        return self._undistort(camera, rgb, mask)

    def close(self) -> None:
        self._smc.close()
        if self._masks is not self._smc:
            self._masks.close()
