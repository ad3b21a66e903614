"""Frame sources of DynaCap captures: per-frame RGBA image folders, per-camera videos and mask folders.

Layouts (dynacap-formats.md 1.11, docs/data.md):

- image folder (DELIFFAS): ``<root>/rgb_<W>_<H>/<frame:06d>/image_alp_c_<cam:03d>_f_<frame:06d>.png``,
  8-bit RGBA; RGB is the image (straight colour, not premultiplied by A), A the foreground coverage.
- videos (raw DynaCap release): ``<seq>/img/c_<name>.avi`` (RGB) and ``<seq>/fg/c_<name>.avi``
  (foreground masks as grey frames), video frame k = capture frame ``first_frame + k``.
- mask folders (DDC scripts): ``<root>/<cam>/image_c_<cam>_f_<frame>.(jpg|png)`` (no zero padding).

Every source answers ``read(frame, camera) -> (rgb (H, W, 3) uint8, mask (H, W) uint8)`` with
``camera`` the camera's index in ``cameras.calibration`` and ``frame`` the capture frame index.
Video sources keep one open decoder per camera and read forward sequentially, seeking only when a
request jumps backwards or far ahead. Video writers use the lossless FFV1 codec (checked to be
available in opencv-python-headless here, bit-exact read-back; MJPG is lossy and is refused).
"""

from __future__ import annotations

import logging
import os
import re
from collections import OrderedDict
from pathlib import Path
from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from deliffas.io.infra.files import temp_path

__all__ = [
    "FrameSource",
    "FramesSpec",
    "ImageFolderSource",
    "VideoSource",
    "MaskFolderSource",
    "image_path",
    "find_image_folder",
    "write_image",
    "VideoWriterSet",
    "video_path",
    "open_frame_source",
    "image_size",
    "VIDEO_CODEC",
    "PNG_COMPRESSION",
]

log = logging.getLogger(__name__)

VIDEO_CODEC = "FFV1"
"""FourCC of the videos we write: FFV1 (lossless intra-only, exact seeks). opencv-headless 5.0 here
also writes HFYU and MPNG losslessly (larger files); MJPG and XVID are lossy (max error 224 on noise)."""

PNG_COMPRESSION = 3
"""zlib level of the PNGs we write (cv2 default 1 is faster but ~15 % larger; 9 gains ~2 % more at 4x time)."""

_RGB_DIR = re.compile(r"^rgb_(\d+)_(\d+)$")


def _cv2():
    import cv2  # opencv is a hard dependency; imported lazily to keep `import deliffas` light

    return cv2


@runtime_checkable
class FrameSource(Protocol):
    """Anything that yields the image and foreground mask of one (frame, camera)."""

    def read(self, frame: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
        """rgb (H, W, 3) uint8 and mask (H, W) uint8 (0 background … 255 foreground)."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class FramesSpec(Protocol):
    """Where a sequence's frames are, picklable: ``open`` gives its ``FrameSource`` in the process that
    reads (``data.subjects.FrameSourceSpec``, ``io.formats.capture_frames.FileFramesSpec``, ``SmcFramesSpec``).

    A spec may set the class attribute ``keep_open = True`` when its source reads any (frame, camera) at one cost
    and is slow to open: a conversion then keeps one source per worker open across shards instead of opening one
    per shard (``SmcFramesSpec``)."""

    def open(self) -> FrameSource: ...

    def image_frames(self) -> set[int] | None:
        """Frame numbers that have images (None: every frame of a video has one)."""
        ...


# --------------------------------------------------------------------------------------------- image folders
def image_path(root: str | os.PathLike, frame: int, camera: int) -> Path:
    """``<root>/<frame:06d>/image_alp_c_<camera:03d>_f_<frame:06d>.png`` (root = the ``rgb_<W>_<H>`` folder)."""
    return Path(root) / f"{frame:06d}" / f"image_alp_c_{camera:03d}_f_{frame:06d}.png"


def find_image_folder(path: str | os.PathLike) -> Path | None:
    """The ``rgb_<W>_<H>`` folder at or directly under ``path`` (None when there is none).

    Raises:
        ValueError: several ``rgb_*_*`` folders (ambiguous resolution).
    """
    p = Path(path)
    if _RGB_DIR.match(p.name) and p.is_dir():
        return p
    if not p.is_dir():
        return None
    found = sorted(q for q in p.iterdir() if q.is_dir() and _RGB_DIR.match(q.name))
    if len(found) > 1:
        raise ValueError(f"{p}: several image folders {[q.name for q in found]}; name one explicitly")
    return found[0] if found else None


def _decode_rgba(data: np.ndarray | None, what: str) -> tuple[np.ndarray, np.ndarray]:
    cv2 = _cv2()
    if data is None:
        raise FileNotFoundError(f"{what}: cannot read image")
    if data.ndim == 2:
        rgb = np.repeat(data[..., None], 3, axis=2)
        return rgb, np.full(data.shape, 255, np.uint8)
    if data.dtype != np.uint8:
        raise ValueError(f"{what}: expected an 8-bit image, got {data.dtype}")
    if data.shape[2] == 4:
        rgb = cv2.cvtColor(data, cv2.COLOR_BGRA2RGB)
        return rgb, np.ascontiguousarray(data[..., 3])
    rgb = cv2.cvtColor(data, cv2.COLOR_BGR2RGB)
    return rgb, np.full(data.shape[:2], 255, np.uint8)


class ImageFolderSource:
    """DELIFFAS per-frame RGBA PNGs: ``<rgb_W_H>/<f:06d>/image_alp_c_<c:03d>_f_<f:06d>.png``.

    Args:
        root: the ``rgb_<W>_<H>`` folder or its parent (e.g. ``<subject>/training``).
        masks: optional mask source that replaces the PNG's alpha (e.g. a ``MaskFolderSource``);
            PNGs without alpha and no ``masks`` get an all-255 mask.
    """

    def __init__(self, root: str | os.PathLike, masks: "MaskFolderSource | None" = None):
        folder = find_image_folder(root)
        if folder is None:
            raise FileNotFoundError(f"{root}: no rgb_<W>_<H> image folder")
        self.root = folder
        m = _RGB_DIR.match(folder.name)
        self.width, self.height = int(m.group(1)), int(m.group(2))
        self.masks = masks

    def path(self, frame: int, camera: int) -> Path:
        return image_path(self.root, frame, camera)

    def frames(self) -> list[int]:
        """Frame indices that have a folder (sorted)."""
        return sorted(int(p.name) for p in self.root.iterdir() if p.is_dir() and p.name.isdigit())

    def read(self, frame: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
        cv2 = _cv2()
        p = self.path(frame, camera)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: image of frame {frame}, camera {camera} not found")
        rgb, mask = _decode_rgba(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), str(p))
        if rgb.shape[:2] != (self.height, self.width):
            raise ValueError(f"{p}: expected {self.width}x{self.height} (folder name), got {rgb.shape[1]}x{rgb.shape[0]}")
        if self.masks is not None:
            mask = self.masks.read_mask(frame, camera)
        return rgb, mask

    def close(self) -> None:
        if self.masks is not None:
            self.masks.close()


def write_image(root: str | os.PathLike, frame: int, camera: int, rgb: np.ndarray, mask: np.ndarray) -> Path:
    """Write one RGBA PNG of the image-folder layout (atomically: temporary name, then rename).

    Args:
        root: the ``rgb_<W>_<H>`` folder.
        rgb: (H, W, 3) uint8.
        mask: (H, W) uint8 alpha.
    """
    cv2 = _cv2()
    p = image_path(root, frame, camera)
    p.parent.mkdir(parents=True, exist_ok=True)
    bgra = np.concatenate([np.ascontiguousarray(rgb[..., ::-1]), mask[..., None]], axis=2)
    ok, buf = cv2.imencode(".png", bgra, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:
        raise RuntimeError(f"{p}: PNG encoding failed")
    tmp = temp_path(p)
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, p)
    return p


# --------------------------------------------------------------------------------------------- mask folders
class MaskFolderSource:
    """DDC mask folders ``<root>/<cam>/image_c_<cam>_f_<frame>.(jpg|png)`` (camera and frame unpadded).

    ``read_mask`` returns (H, W) uint8; JPEG masks are returned as decoded (threshold downstream).
    """

    def __init__(self, root: str | os.PathLike, camera_names: Sequence[str] | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.root}: mask folder not found")
        self.camera_names = list(camera_names) if camera_names is not None else None

    def _name(self, camera: int) -> str:
        return self.camera_names[camera] if self.camera_names is not None else str(camera)

    def read_mask(self, frame: int, camera: int) -> np.ndarray:
        cv2 = _cv2()
        name = self._name(camera)
        for ext in ("png", "jpg", "jpeg"):
            p = self.root / name / f"image_c_{name}_f_{frame}.{ext}"
            if p.is_file():
                m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
                if m is None:
                    raise ValueError(f"{p}: unreadable mask image")
                return m
        raise FileNotFoundError(f"{self.root / name}: no mask image_c_{name}_f_{frame}.(png|jpg)")

    def read(self, frame: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
        """Masks only: rgb is the mask replicated to 3 channels (for inspection)."""
        m = self.read_mask(frame, camera)
        return np.repeat(m[..., None], 3, axis=2), m

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------------------------- videos
def video_path(seq_dir: str | os.PathLike, kind: str, camera_name: str) -> Path:
    """``<seq>/<kind>/c_<camera_name>.avi`` with kind ``img`` or ``fg``."""
    return Path(seq_dir) / kind / f"c_{camera_name}.avi"


def image_size(seq_dir: str | os.PathLike, layout: str, camera_names: Sequence[str]) -> tuple[int, int, str]:
    """(width, height, layout) of a sequence folder's frames; ``layout`` auto picks images when present."""
    seq_dir = Path(seq_dir)
    folder = find_image_folder(seq_dir) if layout in ("auto", "images") else None
    if folder is not None:
        w, h = folder.name.split("_")[1:3]
        return int(w), int(h), "images"
    if layout in ("auto", "videos") and (seq_dir / "img").is_dir():
        cv2 = _cv2()
        cap = cv2.VideoCapture(str(_resolve_video(seq_dir, "img", camera_names[0])))
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        cap.release()
        return w, h, "videos"
    raise FileNotFoundError(f"{seq_dir}: no frames ({'rgb_<W>_<H>/ or img/' if layout == 'auto' else layout})")


def _resolve_video(seq_dir: Path, kind: str, name: str) -> Path:
    """Find the video of a camera; raw releases pad names differently (``c_7``, ``c_07``, ``c_007``)."""
    p = video_path(seq_dir, kind, name)
    if p.is_file():
        return p
    if name.isdigit():
        for width in (2, 3):
            q = video_path(seq_dir, kind, f"{int(name):0{width}d}")
            if q.is_file():
                return q
        q = video_path(seq_dir, kind, str(int(name)))
        if q.is_file():
            return q
    raise FileNotFoundError(f"{p}: video of camera '{name}' not found")


class _Decoder:
    """One open video with its read position and the last decoded frame."""

    def __init__(self, path: Path):
        cv2 = _cv2()
        self.path = path
        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise ValueError(f"{path}: cannot open video")
        self.next_index = 0
        self.last_index = -1
        self.last: np.ndarray | None = None
        self.num_frames = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))

    def get(self, index: int, max_skip: int = 8) -> np.ndarray:
        cv2 = _cv2()
        if index == self.last_index and self.last is not None:
            return self.last
        if index < 0 or (self.num_frames > 0 and index >= self.num_frames):
            raise IndexError(f"{self.path}: frame {index} outside the video's {self.num_frames} frames")
        if index < self.next_index or index > self.next_index + max_skip:
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, index)
            self.next_index = index
        while self.next_index <= index:
            ok, img = self.cap.read()
            if not ok:
                raise IndexError(f"{self.path}: cannot decode frame {self.next_index}")
            self.next_index += 1
        self.last_index, self.last = index, img
        return img

    def close(self) -> None:
        self.cap.release()


class VideoSource:
    """Raw DynaCap videos ``<seq>/img/c_<name>.avi`` + ``<seq>/fg/c_<name>.avi``.

    Args:
        seq_dir: the sequence folder (e.g. ``<subject>/training``).
        camera_names: calibration ``name`` of every camera, by calibration index.
        first_frame: capture frame index of video frame 0.
        max_open: decoders kept open at once (least recently used ones are closed).
        masks: optional mask source replacing the ``fg`` videos.
    """

    def __init__(self, seq_dir: str | os.PathLike, camera_names: Sequence[str], first_frame: int = 0, max_open: int = 32,
                 masks: "MaskFolderSource | None" = None):
        self.seq_dir = Path(seq_dir)
        if not (self.seq_dir / "img").is_dir():
            raise FileNotFoundError(f"{self.seq_dir / 'img'}: no video folder")
        self.camera_names = list(camera_names)
        self.first_frame = int(first_frame)
        self.max_open = max(2, int(max_open))
        self._decoders: OrderedDict[tuple[str, int], _Decoder] = OrderedDict()
        self.masks = masks

    def _decoder(self, kind: str, camera: int) -> _Decoder:
        key = (kind, camera)
        dec = self._decoders.get(key)
        if dec is None:
            if not 0 <= camera < len(self.camera_names):
                raise IndexError(f"camera {camera} outside the {len(self.camera_names)} calibrated cameras")
            dec = _Decoder(_resolve_video(self.seq_dir, kind, self.camera_names[camera]))
            self._decoders[key] = dec
            while len(self._decoders) > self.max_open:
                _, old = self._decoders.popitem(last=False)
                old.close()
        else:
            self._decoders.move_to_end(key)
        return dec

    def read(self, frame: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
        cv2 = _cv2()
        index = int(frame) - self.first_frame
        bgr = self._decoder("img", camera).get(index)
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        if self.masks is not None:
            mask = self.masks.read_mask(frame, camera)
        elif (self.seq_dir / "fg").is_dir():
            fg = self._decoder("fg", camera).get(index)
            mask = np.ascontiguousarray(fg[..., 0]) if fg.ndim == 3 else fg
        else:
            mask = np.full(rgb.shape[:2], 255, np.uint8)
        return rgb, mask

    def close(self) -> None:
        for dec in self._decoders.values():
            dec.close()
        self._decoders.clear()

    def __del__(self):  # decoders hold file handles
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class VideoWriterSet:
    """Writes ``<seq>/img/c_<name>.avi`` and ``<seq>/fg/c_<name>.avi`` (FFV1, lossless) frame by frame.

    Frames must be appended in capture order per camera; ``close`` finalises every file.
    """

    def __init__(self, seq_dir: str | os.PathLike, camera_names: Sequence[str], width: int, height: int,
                 fps: float = 25.0, codec: str = VIDEO_CODEC):
        cv2 = _cv2()
        if codec in ("MJPG", "XVID", "mp4v"):
            raise ValueError(f"video codec {codec} is lossy; use FFV1 (or HFYU/MPNG)")
        self.seq_dir = Path(seq_dir)
        self.size = (int(width), int(height))
        self._writers: dict[tuple[str, int], object] = {}
        self.camera_names = list(camera_names)
        fourcc = cv2.VideoWriter_fourcc(*codec)
        for kind in ("img", "fg"):
            (self.seq_dir / kind).mkdir(parents=True, exist_ok=True)
            for c, name in enumerate(self.camera_names):
                p = video_path(self.seq_dir, kind, name)
                w = cv2.VideoWriter(str(p), fourcc, float(fps), self.size, kind == "img")
                if not w.isOpened():
                    raise RuntimeError(f"{p}: opencv cannot write {codec} video here")
                self._writers[(kind, c)] = w

    def write(self, camera: int, rgb: np.ndarray, mask: np.ndarray) -> None:
        """Append one frame of ``camera``: rgb (H, W, 3) uint8, mask (H, W) uint8."""
        if rgb.shape[:2] != (self.size[1], self.size[0]):
            raise ValueError(f"frame of camera {camera}: expected {self.size[0]}x{self.size[1]}, got {rgb.shape[1]}x{rgb.shape[0]}")
        self._writers[("img", camera)].write(np.ascontiguousarray(rgb[..., ::-1]))
        self._writers[("fg", camera)].write(np.ascontiguousarray(mask))

    def close(self) -> None:
        for w in self._writers.values():
            w.release()
        self._writers.clear()


# --------------------------------------------------------------------------------------------- factory
def open_frame_source(seq_dir: str | os.PathLike, camera_names: Sequence[str], layout: str = "auto",
                      first_frame: int = 0, mask_dir: str | os.PathLike | None = None) -> FrameSource:
    """Open the frames of one sequence folder.

    Args:
        seq_dir: e.g. ``<subject>/training``; holds ``rgb_<W>_<H>/`` and/or ``img/`` + ``fg/``.
        camera_names: calibration names by calibration index (needed for video file names).
        layout: ``images``, ``videos`` or ``auto`` (images when present, else videos).
        first_frame: capture frame of video frame 0.
        mask_dir: optional DDC mask folder replacing the images' alpha or the ``fg`` videos.
    """
    seq = Path(seq_dir)
    masks = MaskFolderSource(mask_dir, camera_names) if mask_dir is not None else None
    if layout not in ("auto", "images", "videos"):
        raise ValueError(f"layout must be auto, images or videos, got {layout!r}")
    if layout in ("auto", "images") and find_image_folder(seq) is not None:
        return ImageFolderSource(seq, masks)
    if layout in ("auto", "videos") and (seq / "img").is_dir():
        return VideoSource(seq, camera_names, first_frame, masks=masks)
    raise FileNotFoundError(f"{seq}: no {'rgb_<W>_<H>/ or img/' if layout == 'auto' else layout} frames found")
