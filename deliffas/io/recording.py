"""A raw multi-view recording: one video (or one image folder) per camera, found, matched to the calibration and read.

``deliffas ingest`` reads a recording folder with these functions, in this order:

- :func:`find_streams`: the videos (``*.mp4 *.avi *.mov *.mkv *.webm``, any case) in ``ROOT/videos/`` or ``ROOT/``,
  else one image folder per camera (``ROOT/images/<cam>/`` or ``ROOT/<cam>/`` holding ``*.jpg *.jpeg *.png``,
  frames in the natural order of their names: ``2.png`` before ``10.png``). Each is a :class:`Stream` with its
  frame count (the container's, else counted by demuxing packets, without decoding), frame rate and size.
- :func:`match_streams`: one stream per calibration camera (exact name, any case, one name inside the other,
  equal numbers: ``cam1`` ~ ``cam01`` ~ ``Camera_1``); extra streams are ignored.
- :func:`check_streams` with :func:`parse_frame_range` (``--frames A:B:STEP``): the frames to read, the same in
  every stream.
- :class:`StreamReader`: the chosen frames as (H, W, 3) uint8 RGB, decoded forward only (PyAV for videos,
  OpenCV for images).

Frames are returned as the file stores them: a video whose container asks players to rotate it is not rotated
(the reader logs a warning), so its calibration must be of the stored frames.

Every problem is a :class:`RecordingError` (a ValueError) naming the file or folder, what was expected and
what to type.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterator, Literal, Sequence

import numpy as np

__all__ = ["RecordingError", "Stream", "VIDEO_SUFFIXES", "IMAGE_SUFFIXES", "find_streams", "match_streams",
           "check_streams", "parse_frame_range", "natural_key", "StreamReader"]

logger = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm")
"""Suffixes of the video files a recording may hold (compared in lower case)."""
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
"""Suffixes of the image files of a camera's image folder (compared in lower case)."""
_FPS_TOLERANCE = 1e-3
"""Relative difference of two frame rates still taken as equal (29.97 and 30 differ)."""


class RecordingError(ValueError):
    """A recording that cannot be read as asked: the message names the file or folder, what was expected and
    what to type."""


@dataclass(frozen=True)
class Stream:
    """One camera's frames in a recording: a video file or a folder of images.

    Attributes:
        camera: the calibration camera name it was matched to (``''`` before :func:`match_streams`).
        path: the video file, or the image folder.
        kind: ``"video"`` or ``"images"``.
        num_frames: frames in the stream (the container's count, or the packets counted, or the image files).
        fps: frames per second of a video (its average rate); None for image folders or a video stating none.
        width: frame width, pixels (as stored, before any rotation a player applies).
        height: frame height, pixels.
    """

    camera: str
    path: Path
    kind: Literal["video", "images"]
    num_frames: int
    fps: float | None
    width: int
    height: int

    @property
    def key(self) -> str:
        """The name matched against camera names: a video's stem, an image folder's name."""
        return self.path.stem if self.kind == "video" else self.path.name


def natural_key(name: str) -> tuple:
    """Sort key putting ``frame2.png`` before ``frame10.png``: digit runs compare as numbers, the rest case-blind."""
    return tuple(int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name))


# ----------------------------------------------------------------------------------------------------- finding


def _video_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES
                   and not p.name.startswith(".")), key=lambda p: natural_key(p.name))


def _image_files(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                   and not p.name.startswith(".")), key=lambda p: natural_key(p.name))


def _image_folders(folder: Path) -> list[tuple[Path, list[Path]]]:
    if not folder.is_dir():
        return []
    out = []
    for sub in sorted((p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")),
                      key=lambda p: natural_key(p.name)):
        files = _image_files(sub)
        if files:
            out.append((sub, files))
    return out


def _count_packets(container: Any, stream: Any) -> int:
    """Video packets of ``stream`` (demuxed, not decoded); the flushing empty packets do not count."""
    return sum(1 for packet in container.demux(stream) if packet.size > 0)


def _probe_video(path: Path) -> Stream:
    """The :class:`Stream` of one video file, from its container (nothing decoded unless it states no size)."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise RecordingError(f"{path}: holds no video stream; a recording needs one video per camera "
                                     f"(remove or rename this file)")
            stream = container.streams.video[0]
            ctx = stream.codec_context
            rate = stream.average_rate or stream.guessed_rate or stream.base_rate
            fps = float(rate) if rate else None
            width, height = int(ctx.width), int(ctx.height)
            if width <= 0 or height <= 0:
                first = next(container.decode(stream), None)
                width, height = (first.width, first.height) if first is not None else (0, 0)
                container.seek(0)
            num = int(stream.frames or 0) or _count_packets(container, stream)
    except (av.FFmpegError, OSError) as err:
        raise RecordingError(f"{path}: not a readable video ({type(err).__name__}: {err}); expected a video "
                             f"(ffprobe '{path}' shows what it holds; re-encode it, e.g. ffmpeg -i '{path}' "
                             f"-c:v libx264 fixed.mp4, or remove it)") from err
    if num <= 0 or width <= 0:
        raise RecordingError(f"{path}: a video of no frames; re-export it or remove it from the recording")
    return Stream("", path, "video", num, fps, width, height)


def _probe_images(folder: Path, files: list[Path]) -> Stream:
    """The :class:`Stream` of one image folder (its first image decoded for the size)."""
    first = _read_image(files[0])
    return Stream("", folder, "images", len(files), None, int(first.shape[1]), int(first.shape[0]))


def find_streams(root: Path) -> list[Stream]:
    """The camera streams of a recording folder, unmatched (``camera == ''``), in natural order of their names.

    Videos in ``root/videos/``, else in ``root/``; without videos, one image folder per camera in
    ``root/images/<cam>/``, else ``root/<cam>/`` (folders holding no image are skipped, e.g. ``calibration/``).

    Args:
        root: the recording folder.

    Returns:
        One :class:`Stream` per video file or image folder.

    Raises:
        RecordingError: ``root`` is not a folder, holds no stream, or holds a video that does not open.
    """
    root = Path(root)
    if not root.is_dir():
        raise RecordingError(f"{root}: recording folder not found; give the folder holding videos/ (or images/<cam>/)"
                             f" and the calibration")
    for folder in (root / "videos", root):
        videos = _video_files(folder)
        if videos:
            logger.info("%s: %d videos", folder, len(videos))
            return [_probe_video(p) for p in videos]
    for folder in (root / "images", root):
        folders = _image_folders(folder)
        if folders:
            logger.info("%s: %d image folders", folder, len(folders))
            return [_probe_images(sub, files) for sub, files in folders]
    videos, images = (" ".join("*" + s for s in suffixes) for suffixes in (VIDEO_SUFFIXES, IMAGE_SUFFIXES))
    raise RecordingError(
        f"{root}: no camera streams found; expected one video per camera ({videos})"
        f" in {root / 'videos'}/ or {root}/, or one image folder per camera ({images})"
        f" in {root / 'images'}/<cam>/ or {root}/<cam>/; e.g. mkdir '{root / 'videos'}' and move the videos there, "
        f"each named after its calibration camera (cam01.mp4)")


# ----------------------------------------------------------------------------------------------------- matching


def _digits(name: str) -> tuple[int, ...]:
    return tuple(int(d) for d in re.findall(r"\d+", name))


def _tier_matches(tier: int, name: str, key: str) -> bool:
    """Whether stream name ``key`` matches camera ``name`` at ``tier`` (0 exact, 1 any case, 2 inside, 3 numbers)."""
    if tier == 0:
        return key == name
    if tier == 1:
        return key.lower() == name.lower()
    if tier == 2:
        return bool(name) and (name.lower() in key.lower() or key.lower() in name.lower())
    digits = _digits(name)
    return bool(digits) and digits == _digits(key)


def _assign_tier(tier: int, names: Sequence[str], streams: Sequence[Stream], chosen: dict[int, int],
                 ambiguous: dict[int, list[int]]) -> None:
    """Match the open cameras at one tier, repeating while a unique match frees another camera's choice."""
    while True:
        taken = set(chosen.values())
        claims: dict[int, list[int]] = {}
        open_cands = {}
        for c, name in enumerate(names):
            if c in chosen or c in ambiguous:
                continue
            cands = [s for s, st in enumerate(streams) if s not in taken and _tier_matches(tier, name, st.key)]
            open_cands[c] = cands
            if len(cands) == 1:
                claims.setdefault(cands[0], []).append(c)
        won = {cams[0]: s for s, cams in claims.items() if len(cams) == 1}
        if not won:
            break
        chosen.update(won)
    for c, cands in open_cands.items():
        if cands:  # several streams, or one stream wanted by several cameras: ambiguous at this tier
            ambiguous[c] = cands


def _match_table(names: Sequence[str], streams: Sequence[Stream], chosen: dict[int, int],
                 ambiguous: dict[int, list[int]]) -> str:
    width = max(len("camera"), *(len(n) for n in names))
    rows = [f"  {'camera':<{width}}  stream(s)"]
    for c, name in enumerate(names):
        if c in chosen:
            cell = streams[chosen[c]].path.name
        elif c in ambiguous:
            cell = "AMBIGUOUS: " + ", ".join(streams[s].path.name for s in ambiguous[c])
        else:
            cell = "MISSING: no stream matches"
        rows.append(f"  {name:<{width}}  {cell}")
    return "\n".join(rows)


def match_streams(camera_names: Sequence[str], streams: Sequence[Stream]) -> list[Stream]:
    """One stream per calibration camera, in camera order, each with ``camera`` set to its name.

    A camera matches the stream whose name (a video's stem, an image folder's name) is, in this order of
    preference: its name; its name in another case; a name containing it or contained in it (any case); a name of
    the same numbers (``cam1`` ~ ``cam01`` ~ ``Camera_1``). A match must be unique: a camera with several
    candidates at its first matching tier, or a stream wanted by several cameras, is ambiguous. Streams no camera
    matches are ignored (logged at INFO).

    Args:
        camera_names: the calibration's camera names, in its order.
        streams: the recording's streams (:func:`find_streams`).

    Returns:
        ``len(camera_names)`` streams; ``result[i].camera == camera_names[i]``.

    Raises:
        RecordingError: a camera with no stream or with an ambiguous match; the message tabulates every camera's
            stream(s) and says to rename the files or pass ``--cameras NAME,...``.
    """
    names = list(camera_names)
    if not streams:
        raise RecordingError("no streams to match the calibration cameras to; a recording needs one video or image "
                             "folder per camera")
    chosen: dict[int, int] = {}
    ambiguous: dict[int, list[int]] = {}
    for tier in range(4):
        _assign_tier(tier, names, streams, chosen, ambiguous)
    where = streams[0].path.parent
    if len(chosen) < len(names):
        missing = [names[c] for c in range(len(names)) if c not in chosen]
        raise RecordingError(
            f"{where}: cannot match {len(missing)} of the {len(names)} calibration cameras ({', '.join(missing)}) to "
            f"one stream each (streams: {', '.join(s.path.name for s in streams)}):\n"
            f"{_match_table(names, streams, chosen, ambiguous)}\n"
            f"Rename the files so each is named after its camera (e.g. {names[0]}{_example_suffix(streams)}), or "
            f"pass --cameras NAME,... to use only the calibration cameras that have a stream")
    extra = sorted(set(range(len(streams))) - set(chosen.values()))
    if extra:
        logger.info("%s: ignoring %d streams no calibration camera matches: %s", where, len(extra),
                    ", ".join(streams[s].path.name for s in extra))
    for c, name in enumerate(names):
        logger.debug("camera %s <- %s", name, streams[chosen[c]].path)
    return [replace(streams[chosen[c]], camera=name) for c, name in enumerate(names)]


def _example_suffix(streams: Sequence[Stream]) -> str:
    return streams[0].path.suffix.lower() if streams[0].kind == "video" else "/"


# ----------------------------------------------------------------------------------------------------- checking


def parse_frame_range(text: str) -> tuple[int, int, int]:
    """``--frames`` text as ``(start, stop, step)``: ``A:B``, ``A:B:STEP``, ``:B`` (from 0), ``A:`` (to the end).

    Args:
        text: the option's text; A, B, STEP non-negative integers, stop exclusive, STEP >= 1 (default 1).

    Returns:
        ``(start, stop, step)`` frame indices; ``stop == -1`` means the end of the streams.

    Raises:
        ValueError: text of another form, a negative number, STEP 0, or B <= A.
    """
    parts = text.strip().split(":")
    usage = f"--frames {text!r}: expected A:B or A:B:STEP (frame indices, B exclusive; e.g. 0:100:2, :50 or 10:)"
    if len(parts) not in (2, 3):
        raise ValueError(usage)
    try:
        nums = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise ValueError(usage) from None
    if any(n is not None and n < 0 for n in nums):
        raise ValueError(f"{usage}; the numbers cannot be negative")
    start = nums[0] or 0
    stop = -1 if nums[1] is None else nums[1]
    step = 1 if len(nums) == 2 or nums[2] is None else nums[2]
    if step < 1:
        raise ValueError(f"{usage}; STEP must be at least 1")
    if stop != -1 and stop <= start:
        raise ValueError(f"{usage}; B must be greater than A")
    return start, stop, step


def _stream_rows(streams: Sequence[Stream]) -> str:
    width = max(len(s.camera or s.key) for s in streams)
    return "\n".join(f"  {s.camera or s.key:<{width}}  {s.path.name}: {s.num_frames} frames, "
                     f"{'no frame rate' if s.fps is None else f'{s.fps:g} fps'}" for s in streams)


def _check_fps(streams: Sequence[Stream], where: Path) -> None:
    rates = [s.fps for s in streams if s.fps is not None]
    if rates and max(rates) - min(rates) > _FPS_TOLERANCE * max(rates):
        raise RecordingError(
            f"{where}: the streams have different frame rates, so their frame i are not the same instant:\n"
            f"{_stream_rows(streams)}\n"
            f"Re-encode them at one rate, synchronised (e.g. ffmpeg -i IN -r {max(rates):g} OUT), or extract the "
            f"synchronised frames into images/<cam>/ folders")


def check_streams(streams: Sequence[Stream], frames: tuple[int, int, int] | None) -> range:
    """The frame indices to read from every stream, after checking that the streams agree.

    Args:
        streams: the matched streams (:func:`match_streams`).
        frames: ``(start, stop, step)`` of ``--frames`` (:func:`parse_frame_range`; stop exclusive, -1 = the
            end), or None for every frame.

    Returns:
        The frame indices (0-based, in each stream's frame order), non-empty.

    Raises:
        RecordingError: streams of different frame rates (always), streams of different frame counts when
            ``frames`` is None or reaches past the shortest stream (the message lists every stream's count and
            rate and the ``--frames A:B`` that cuts to the common part), or a range past the streams' end.
    """
    if not streams:
        raise RecordingError("no streams to read; a recording needs one video or image folder per camera")
    where = streams[0].path.parent
    _check_fps(streams, where)
    counts = [s.num_frames for s in streams]
    common = min(counts)
    start, stop, step = frames if frames is not None else (0, -1, 1)
    cut = f"--frames {start}:{common}" + (f":{step}" if step != 1 else "")
    if stop == -1 and len(set(counts)) > 1:
        raise RecordingError(
            f"{where}: the streams have different frame counts, so 'to the end' is not the same frame in each:\n"
            f"{_stream_rows(streams)}\n"
            f"Pass {cut} to read the common part (if the streams start at the same instant), or trim the videos")
    asked = f"{start}:{'' if stop == -1 else stop}"
    stop = common if stop == -1 else stop
    if stop > common or start >= stop:
        raise RecordingError(
            f"{where}: --frames {asked} reaches past the end of the shortest stream ({common} frames):\n"
            f"{_stream_rows(streams)}\n"
            f"Pass --frames A:B with B <= {common}" + (f" (e.g. {cut})" if start < common else ""))
    return range(start, stop, step)


# ----------------------------------------------------------------------------------------------------- reading


def _read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file (any 8/16-bit, grey or colour, through ``cv2.IMREAD_COLOR``)."""
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise RecordingError(f"{path}: not a readable image; expected a .jpg/.jpeg/.png file (re-export it, or "
                             f"remove it and renumber the frames after it)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class StreamReader:
    """Frames of one :class:`Stream`, decoded forward only; a context manager that closes the video.

    Usage::

        with StreamReader(stream) as reader:
            for index, rgb in reader.frames(range(0, 100, 5)):   # rgb: (H, W, 3) uint8
                ...
    """

    def __init__(self, stream: Stream):
        """Open nothing yet: the video opens at the first :meth:`frames` call.

        Args:
            stream: a stream of :func:`find_streams` (matched or not).
        """
        self.stream = stream
        self._container: Any = None
        self._decoded: Iterator[Any] | None = None
        self._next = 0  # index of the next frame the decoder gives
        self._files: list[Path] | None = None
        self._warned_rotation = False

    def __enter__(self) -> StreamReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the video (again harmless)."""
        if self._container is not None:
            self._container.close()
        self._container, self._decoded, self._next = None, None, 0

    def frames(self, indices: range) -> Iterator[tuple[int, np.ndarray]]:
        """``(index, rgb)`` for each index, in order; rgb (H, W, 3) uint8 RGB, H x W the stream's height x width.

        A video is decoded sequentially; the frames not asked for are decoded but not converted. A later call
        continues forward from where the last one stopped (a call asking for earlier frames reopens the video).

        Args:
            indices: frame indices (0-based), increasing (a ``range`` with a positive step).

        Raises:
            RecordingError: a video that ends (or fails to decode) before an asked frame, a frame of another size,
                or an unreadable image file; each naming the file and the frame.
            ValueError: a decreasing range, or a negative index.
        """
        if indices.step < 1:
            raise ValueError(f"{self.stream.path}: frames must be read forward, got {indices}")
        if len(indices) and indices[0] < 0:
            raise ValueError(f"{self.stream.path}: negative frame index in {indices}")
        if self.stream.kind == "images":
            return self._image_frames(indices)
        return self._video_frames(indices)

    def _image_frames(self, indices: range) -> Iterator[tuple[int, np.ndarray]]:
        if self._files is None:
            self._files = _image_files(self.stream.path)
        files = self._files
        for i in indices:
            if i >= len(files):
                raise RecordingError(f"{self.stream.path}: frame {i} asked for, the folder holds {len(files)} images "
                                     f"(were some removed? pass --frames A:B with B <= {len(files)})")
            rgb = _read_image(files[i])
            self._check_size(rgb, i, files[i])
            yield i, rgb

    def _check_size(self, rgb: np.ndarray, index: int, where: Path) -> None:
        if rgb.shape[:2] != (self.stream.height, self.stream.width):
            raise RecordingError(f"{where}: frame {index} is {rgb.shape[1]}x{rgb.shape[0]}, the stream's first frame "
                                 f"{self.stream.width}x{self.stream.height}; every frame of a camera must have one "
                                 f"size (re-export it at {self.stream.width}x{self.stream.height})")

    def _open(self) -> None:
        import av

        self.close()
        try:
            self._container = av.open(str(self.stream.path))
            vstream = self._container.streams.video[0]
            vstream.codec_context.thread_type = "AUTO"
            self._decoded = self._container.decode(vstream)
        except (av.FFmpegError, OSError, IndexError) as err:
            self.close()
            raise RecordingError(f"{self.stream.path}: not a readable video ({type(err).__name__}: {err}); "
                                 f"re-encode it (ffmpeg -i IN -c:v libx264 OUT.mp4) or remove it") from err

    def _next_frame(self, wanted: int) -> Any:
        """The next decoded frame (``self._next``), or a RecordingError naming the frame ``wanted``."""
        import av

        path = self.stream.path
        try:
            frame = next(self._decoded, None)
        except (av.FFmpegError, OSError) as err:
            raise RecordingError(f"{path}: frame {self._next} does not decode ({type(err).__name__}: {err}), before "
                                 f"frame {wanted}; re-encode the video or pass --frames A:B with B <= {self._next}"
                                 ) from err
        if frame is None:
            raise RecordingError(f"{path}: the video ends after {self._next} frames, frame {wanted} was asked for "
                                 f"(its container claims {self.stream.num_frames}); pass --frames A:B with "
                                 f"B <= {self._next}")
        if frame.rotation and not self._warned_rotation:
            self._warned_rotation = True
            logger.warning("%s: the video asks players to rotate it by %s degrees; its frames are read as stored "
                           "(%dx%d), so the calibration must be of the stored frames", path, frame.rotation,
                           frame.width, frame.height)
        self._next += 1
        return frame

    def _video_frames(self, indices: range) -> Iterator[tuple[int, np.ndarray]]:
        for i in indices:
            if self._decoded is None or i < self._next:
                self._open()
            frame = self._next_frame(i)
            while self._next <= i:
                frame = self._next_frame(i)
            rgb = frame.to_ndarray(format="rgb24")
            self._check_size(rgb, i, self.stream.path)
            yield i, rgb
