"""Videos people can open: H.264 ``.mp4`` (and Motion-JPEG ``.avi``) written with PyAV, atomically.

``.mp4`` is H.264 (libx264, yuv420p, ``+faststart``), which browsers, phones and every player open;
yuv420p needs even sides, so an odd-sized frame gets one black row/column (logged). The file is
written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import logging
import os
from fractions import Fraction
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from deliffas.io.infra.files import atomic_path

__all__ = ["VIDEO_SUFFIXES", "write_video", "read_video_info"]

logger = logging.getLogger(__name__)

VIDEO_SUFFIXES = {".mp4": ("libx264", "yuv420p"), ".avi": ("mjpeg", "yuvj420p")}
"""Suffix -> (PyAV codec, pixel format) of the videos deliffas writes."""


# frames: Iterable[Any], not Iterable[np.ndarray]: beartype checks the first item of an iterable that
# looks re-iterable, and a tqdm over a generator does look so (the check would eat a frame).
def write_video(path: str | os.PathLike, frames: Iterable[Any], fps: float, crf: int = 18) -> int:
    """Write (H, W, 3) uint8 RGB frames as a video chosen by ``path``'s suffix; returns the frame count.

    Raises:
        ValueError: an unknown suffix, a non-positive ``fps``, no frames, or frames of another shape/dtype.
    """
    import av

    out = Path(path)
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"{out}: a video must end in {' or '.join(VIDEO_SUFFIXES)}")
    if not fps > 0:
        raise ValueError(f"fps: expected a positive number, got {fps}")
    codec, pix_fmt = VIDEO_SUFFIXES[out.suffix.lower()]
    count, shape = 0, None
    with atomic_path(out, keep_suffix=True) as tmp, av.open(str(tmp), "w") as container:
        stream = None
        for frame in frames:
            frame = np.asarray(frame)
            if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
                raise ValueError(f"{out}: frame {count}: expected (H, W, 3) uint8, got {frame.shape} {frame.dtype}")
            if stream is None:
                shape = frame.shape
                h, w = shape[0] + shape[0] % 2, shape[1] + shape[1] % 2
                if (h, w) != shape[:2]:
                    logger.info("%s: %dx%d padded to %dx%d (the codec needs even sides)", out, shape[1],
                                shape[0], w, h)
                stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
                stream.width, stream.height, stream.pix_fmt = w, h, pix_fmt
                if codec == "libx264":
                    stream.options = {"crf": str(crf), "preset": "medium"}
            if frame.shape != shape:
                raise ValueError(f"{out}: frame {count}: shape {frame.shape}, the first was {shape}")
            padded = np.zeros((stream.height, stream.width, 3), np.uint8)
            padded[:shape[0], :shape[1]] = frame
            for packet in stream.encode(av.VideoFrame.from_ndarray(padded, format="rgb24")):
                container.mux(packet)
            count += 1
        if stream is None:
            raise ValueError(f"{out}: no frames to write")
        for packet in stream.encode():
            container.mux(packet)
    return count


def read_video_info(path: str | os.PathLike) -> dict:
    """Codec name, frame count, width, height and fps of a video (for checks and tests)."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(stream))
        return {"codec": stream.codec_context.name, "frames": frames, "width": stream.codec_context.width,
                "height": stream.codec_context.height, "fps": float(stream.average_rate or 0)}
