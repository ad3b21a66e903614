"""From a stream's decoded frames to the subject's images: undistorted, cropped to one aspect, resized.

A stream a few pixels smaller than its calibration (a 1088-wide sensor stored as a 1080-wide video) is the
calibrated image cropped at the right and bottom (pixel coordinates kept); a stream of another resolution
with the same aspect ratio is the calibrated image scaled. Every camera of a subject has one image size, so
each is then cropped (right/bottom, at most :data:`MAX_CROP` of a side) to the common aspect and resized.
The cameras returned are pinhole cameras that project exactly into the images returned.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np
from jaxtyping import UInt8

from deliffas.io.camera_conventions import DISTORTION, camera_distortion
from deliffas.io.cameras import Camera
from deliffas.io.formats.capture_frames import Undistortion, undistort_maps

__all__ = ["MAX_CROP", "FramePlan", "plan_frames", "output_size"]

log = logging.getLogger(__name__)

MAX_CROP = 0.02
"""The largest fraction of an image side cropped away to reconcile a stream with its calibration."""


@dataclass(frozen=True)
class FramePlan:
    """How one camera's stream frames become subject images.

    Attributes:
        camera: the pinhole camera of the output image (no distortion), at ``size``.
        crop: (w, h) kept from the top-left of the undistorted stream frame.
        size: (W, H) of the output image.
        maps: ``cv2.remap`` tables (H_s, W_s) float32 of the undistortion at the stream size, or None.
        note: what was reconciled ('' when the stream matched the calibration).
    """
    camera: Camera
    crop: tuple[int, int]
    size: tuple[int, int]
    maps: tuple[np.ndarray, np.ndarray] | None
    note: str

    def __call__(self, rgb: UInt8[np.ndarray, "Hs Ws 3"]) -> UInt8[np.ndarray, "H W 3"]:
        """The output image of one decoded (H_s, W_s, 3) uint8 frame."""
        import cv2

        if self.maps is not None:
            rgb = cv2.remap(rgb, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        rgb = rgb[: self.crop[1], : self.crop[0]]
        if (rgb.shape[1], rgb.shape[0]) != self.size:
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(rgb)


def _fit_to_stream(cam: Camera, w: int, h: int, where: str) -> tuple[Camera, str]:
    """``cam`` for a stream frame of ``w`` x ``h``: cropped (a few pixels short) or scaled (same aspect)."""
    if (w, h) == (cam.width, cam.height):
        return cam, ""
    if w <= cam.width and h <= cam.height and (cam.width - w) <= MAX_CROP * cam.width \
            and (cam.height - h) <= MAX_CROP * cam.height:
        return replace(cam, width=w, height=h), f"stream {w}x{h} is the calibrated {cam.width}x{cam.height} cropped"
    if abs(w / h - cam.width / cam.height) <= 0.005 * cam.width / cam.height:
        return cam.rescaled(w, h), f"stream {w}x{h} is the calibrated {cam.width}x{cam.height} scaled"
    raise ValueError(f"{where}: the video is {w}x{h} but camera {cam.name!r} of the calibration is {cam.width}x"
                     f"{cam.height} (neither a crop of at most {MAX_CROP:.0%} nor the same aspect ratio); check that "
                     f"the calibration belongs to this recording, or match the cameras with --cameras")


def output_size(aspect: float, size: tuple[int, int] | int) -> tuple[int, int]:
    """(W, H) of the output images: ``size`` as given, or its long side with ``aspect`` = W / H kept (even sides)."""
    if not isinstance(size, int):
        return int(size[0]), int(size[1])
    if aspect >= 1:
        return size, max(2, 2 * round(size / aspect / 2))
    return max(2, 2 * round(size * aspect / 2)), size


def plan_frames(cameras: Sequence[Camera], stream_sizes: Sequence[tuple[int, int]], where: Sequence[str | Path],
                size: tuple[int, int] | int) -> list[FramePlan]:
    """One :class:`FramePlan` per camera (the calibration's cameras, each stream's (w, h), each stream's path).

    Raises:
        ValueError: a stream that is neither a small crop nor a scaling of its camera, or cameras whose aspect
            ratios differ by more than :data:`MAX_CROP`; naming the file and what to do.
    """
    fitted = [_fit_to_stream(c, w, h, str(p)) for c, (w, h), p in zip(cameras, stream_sizes, where)]
    aspect = min(c.width for c, _ in fitted) / min(c.height for c, _ in fitted)  # the part every camera has
    out_w, out_h = output_size(aspect, size)
    aspect = out_w / out_h
    plans = []
    for (cam, note), p in zip(fitted, where):
        cw, ch = (cam.width, min(cam.height, round(cam.width / aspect))) if cam.width / cam.height <= aspect \
            else (min(cam.width, round(cam.height * aspect)), cam.height)
        cw, ch = min(cw, cam.width), min(ch, cam.height)
        if cw < (1 - MAX_CROP) * cam.width or ch < (1 - MAX_CROP) * cam.height:
            raise ValueError(f"{p}: camera {cam.name!r} is {cam.width}x{cam.height}, the output {out_w}x{out_h}: "
                             f"its aspect ratio differs from the others' by more than {MAX_CROP:.0%}; give --size WxH "
                             "of this camera's aspect or leave it out with --cameras")
        d = camera_distortion(cam)
        maps = None
        if np.any(d != 0):
            K = np.array(cam.K, np.float64)
            K[:2, 2] -= 0.5  # OpenCV pixel centres
            maps = undistort_maps(Undistortion(K, d), cam.width, cam.height)
        pinhole = replace(cam, width=cw, height=ch, extra={k: v for k, v in cam.extra.items() if k != DISTORTION})
        if (cw, ch) != (cam.width, cam.height):
            note = "; ".join(x for x in (note, f"cropped to {cw}x{ch}") if x)
        plans.append(FramePlan(pinhole.rescaled(out_w, out_h), (cw, ch), (out_w, out_h), maps, note))
        if note:
            log.info("%s: %s", p, note)
    return plans
