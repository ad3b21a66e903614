"""Skeletool ``cameras.calibration`` files: pinhole cameras, static or animated (formats doc 1.9)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.io.cameras import Camera, check_camera_names
from deliffas.io.camera_conventions import require_distortion_fits
from deliffas.io.infra.text_lines import DynaCapFormatError, TextLines, write_text_atomic
from deliffas.io.format_registry import CameraWriteOptions, CaptureFormat
from deliffas.io.formats.camera_files import file_detector

PathLike = str | os.PathLike

__all__ = ["read_calibration", "write_calibration", "CALIBRATION_HEADER"]

CALIBRATION_HEADER = "Skeletool Camera Calibration File V1.0"


def _camera_from_keys(path: PathLike, keys: dict, name: str, line: int) -> Camera:
    """The Camera of one camera (or frame block) from its keys; refuses a missing key or a non-rigid extrinsic."""
    for key in ("size", "intrinsic", "extrinsic"):
        if key not in keys:
            raise DynaCapFormatError(path, line, f"camera '{name}' lacks its '{key}' line")
    K4, E = keys["intrinsic"], keys["extrinsic"]
    if abs(E[3, 3] - 1) > 1e-6 or np.abs(E[3, :3]).max() > 1e-6:
        raise DynaCapFormatError(path, line, f"camera '{name}': extrinsic last row must be 0 0 0 1")
    try:
        return Camera(name, K4[:3, :3].copy(), E.copy(), keys["size"][0], keys["size"][1],
                      keys.get("sensor"), keys.get("radial", 0.0))
    except ValueError as err:  # singular intrinsics, a scaled or mirrored rotation
        raise DynaCapFormatError(path, line, f"camera '{name}': {err}") from None


def _read_camera_key(t: TextLines, key: str, vals: list[str], target: dict) -> None:
    """One ``sensor``, ``size``, ``animated``, ``intrinsic``, ``extrinsic`` or ``radial`` line into ``target``
    (the camera, or its current frame block for the last three)."""
    if key == "sensor":
        if len(vals) != 2:
            raise t.error(f"expected 'sensor w h', got {len(vals)} values")
        target["sensor"] = tuple(t.floats(vals, "sensor size"))
    elif key == "size":
        if len(vals) != 2:
            raise t.error(f"expected 'size W H', got {len(vals)} values")
        w, h = (t.to_int(v, "image size") for v in vals)
        if w <= 0 or h <= 0:
            raise t.error(f"expected a positive image size, got {w}x{h}")
        target["size"] = (w, h)
    elif key == "animated":
        if vals not in (["0"], ["1"]):
            raise t.error(f"expected 'animated 0' or 'animated 1', got {' '.join(vals)[:20]!r}")
        target["animated"] = vals == ["1"]
    elif key in ("intrinsic", "extrinsic"):
        if len(vals) != 16:
            raise t.error(f"expected 16 numbers after '{key}' (row-major 4x4), got {len(vals)}")
        target[key] = np.array(t.floats(vals, key)).reshape(4, 4)
    elif vals:  # radial
        target["radial"] = t.to_float(vals[0], "radial coefficient")


def _start_camera(t: TextLines, vals: list[str], names: list[str]) -> dict:
    """The record of a camera's ``name`` line; ``names`` (the file's names so far) must stay unique."""
    if len(vals) != 1:
        raise t.error(f"expected 'name <id>', got {len(vals)} values")
    names.append(vals[0])
    try:
        check_camera_names(names)
    except ValueError as err:  # a second camera of one name would replace the first in every lookup
        raise t.error(str(err)) from None
    return {"name": vals[0], "line": t.line_no, "frames": set()}


def read_calibration(path: PathLike) -> list[Camera]:
    """Read ``cameras.calibration`` into Cameras (formats doc 1.9).

    Animated cameras (``animated 1``) become one Camera per ``frame`` block, named
    ``<name>@<frame>`` (as DELIFFAS reads free-viewpoint paths: one camera per extrinsic). A frame
    block takes its own ``intrinsic``/``radial`` when it has them, else the latest ones of that
    camera; every frame block needs its ``extrinsic``.

    Raises:
        DynaCapFormatError: naming the line, for a missing or malformed key, a frame block without
            its extrinsic, a repeated frame or camera name, or a camera that fails ``check_camera``.
    """
    t = TextLines(path, what="calibration file")
    t.header((CALIBRATION_HEADER,))
    cams: list[Camera] = []
    names: list[str] = []  # every camera's name so far (unique)
    cam: dict | None = None  # the camera being read: name, line, sensor, size, animated, and its latest keys
    block: dict | None = None  # the current frame block of an animated camera: frame, line, and its keys

    def emit(keys: dict, name: str, line: int) -> None:
        cams.append(_camera_from_keys(path, keys, name, line))

    def close_block() -> None:
        nonlocal block
        if block is None:
            return
        if "extrinsic" not in block:
            raise DynaCapFormatError(path, block["line"], f"camera '{cam['name']}' frame {block['frame']} lacks its "
                                                          "'extrinsic' line")
        emit({**cam, **block}, f"{cam['name']}@{block['frame']}", block["line"])
        for key in ("intrinsic", "radial"):  # later frames without their own take these
            if key in block:
                cam[key] = block[key]
        block = None

    def close_camera() -> None:
        if cam is None:
            return
        if cam.get("animated"):
            close_block()
            if not cam["frames"]:
                raise DynaCapFormatError(path, cam["line"], f"animated camera '{cam['name']}' has no 'frame' block")
        else:
            emit(cam, cam["name"], cam["line"])

    while not t.at_end():
        toks = t.next("a calibration line").split()
        key, vals = toks[0], toks[1:]
        if key == "name":
            close_camera()
            cam = _start_camera(t, vals, names)
            continue
        if cam is None:
            raise t.error(f"expected 'name <id>' before '{key}'")
        if key in ("sensor", "size", "animated"):
            _read_camera_key(t, key, vals, cam)
        elif key == "frame":
            if not cam.get("animated"):
                raise t.error(f"'frame' block in camera '{cam['name']}', which is not 'animated 1'")
            close_block()
            frame = t.to_int(vals[0], "frame") if vals else 0
            if frame in cam["frames"]:
                raise t.error(f"camera '{cam['name']}' has frame {frame} twice")
            cam["frames"].add(frame)
            block = {"frame": frame, "line": t.line_no}
        elif key in ("intrinsic", "extrinsic", "radial"):
            _read_camera_key(t, key, vals, block if block is not None else cam)
        elif key in ("polynomial", "polynomialC2W", "polynomialW2C", "imageCircleRadius", "affine"):
            cam.setdefault("extra", {})[key] = vals  # fisheye model: kept out of the pinhole projection
        else:
            raise t.error(f"expected a calibration key (name, sensor, size, animated, frame, intrinsic, extrinsic, "
                          f"radial), got '{key[:30]}'")
    close_camera()
    if not cams:
        raise DynaCapFormatError(path, 0, "expected at least one camera, got none")
    return cams


def write_calibration(path: PathLike, cameras: list[Camera], crlf: bool = False) -> None:
    """Write static cameras in the C++ ``saveCameras`` layout (full precision)."""
    out = [CALIBRATION_HEADER]
    for c in cameras:
        K4 = np.eye(4)
        K4[:3, :3] = c.K
        sensor = c.sensor if c.sensor is not None else (10.0, 10.0 * c.height / c.width)
        out += [
            f"name          {c.name}",
            f"  sensor      {sensor[0]!r} {sensor[1]!r}",
            f"  size        {c.width} {c.height}",
            "  animated    0",
            "  intrinsic   " + " ".join(repr(float(v)) for v in K4.ravel()),
            "  extrinsic   " + " ".join(repr(float(v)) for v in c.world_to_cam.ravel()),
            f"  radial      {c.radial!r}",
        ]
    write_text_atomic(path, "\n".join(out) + "\n", crlf)


# ----------------------------------------------------------------------------------- capture format
def _write_cameras(cameras: Sequence[Camera], out: Path, options: CameraWriteOptions) -> Path:
    cams = [require_distortion_fits(c, "DynaCap .calibration", (), options.drop_distortion, radial_fits=True)
            for c in cameras]
    out.parent.mkdir(parents=True, exist_ok=True)
    write_calibration(out, cams)
    return out


FORMAT = CaptureFormat(
    "dynacap", "DynaCap / Skeletool cameras.calibration", camera_path="cameras.calibration", distortion=(),
    stores_size=True, detect_cameras=file_detector("cameras.calibration", suffixes=(".calibration",)),
    read_cameras=lambda path, size: read_calibration(path), write_cameras=_write_cameras)
"""The cameras of this format, registered by ``deliffas.io.formats.builtin``."""
