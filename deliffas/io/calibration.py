"""Skeletool ``cameras.calibration`` files: pinhole cameras, static or animated (formats doc 1.9)."""

from __future__ import annotations

import os

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.text_lines import DynaCapFormatError, TextLines, write_text_atomic

PathLike = str | os.PathLike

__all__ = ["read_calibration", "write_calibration", "CALIBRATION_HEADER"]

CALIBRATION_HEADER = "Skeletool Camera Calibration File V1.0"


def read_calibration(path: PathLike) -> list[Camera]:
    """Read ``cameras.calibration`` into Cameras (formats doc 1.9).

    Animated cameras become one Camera per ``frame`` block, named ``<name>@<frame>`` (as DELIFFAS
    reads free-viewpoint paths: one camera per extrinsic).
    """
    t = TextLines(path, what="calibration file")
    t.header((CALIBRATION_HEADER,))
    cams: list[Camera] = []
    cur: dict | None = None

    def flush():
        if cur is None:
            return
        for key in ("size", "intrinsic", "extrinsic"):
            if key not in cur:
                raise DynaCapFormatError(path, cur["line"], f"camera '{cur['name']}' lacks its '{key}' line")
        suffix = f"@{cur['frame']}" if cur.get("frame") is not None else ""
        K4, E = cur["intrinsic"], cur["extrinsic"]
        if abs(E[3, 3] - 1) > 1e-6 or np.abs(E[3, :3]).max() > 1e-6:
            raise DynaCapFormatError(path, cur["line"], f"camera '{cur['name']}': extrinsic last row must be 0 0 0 1")
        try:
            cams.append(Camera(cur["name"] + suffix, K4[:3, :3].copy(), E.copy(), cur["size"][0], cur["size"][1],
                               cur.get("sensor"), cur.get("radial", 0.0)))
        except ValueError as err:  # e.g. singular intrinsics
            raise DynaCapFormatError(path, cur["line"], f"camera '{cur['name']}': {err}") from None

    while not t.at_end():
        toks = t.next("a calibration line").split()
        key, vals = toks[0], toks[1:]
        if key == "name":
            if cur is not None and not cur.get("emitted"):
                flush()
            if len(vals) != 1:
                raise t.error(f"expected 'name <id>', got {len(vals)} values")
            cur = {"name": vals[0], "line": t.line_no}
            continue
        if cur is None:
            raise t.error(f"expected 'name <id>' before '{key}'")
        if key == "sensor":
            if len(vals) != 2:
                raise t.error(f"expected 'sensor w h', got {len(vals)} values")
            cur["sensor"] = tuple(t.floats(vals, "sensor size"))
        elif key == "size":
            if len(vals) != 2:
                raise t.error(f"expected 'size W H', got {len(vals)} values")
            w, h = (t.to_int(v, "image size") for v in vals)
            if w <= 0 or h <= 0:
                raise t.error(f"expected a positive image size, got {w}x{h}")
            cur["size"] = (w, h)
        elif key == "animated":
            cur["animated"] = vals == ["1"]
        elif key == "frame":
            if cur.get("frame") is not None and "extrinsic" in cur:
                flush()
            cur["frame"] = t.to_int(vals[0], "frame") if vals else 0
        elif key in ("intrinsic", "extrinsic"):
            if len(vals) != 16:
                raise t.error(f"expected 16 numbers after '{key}' (row-major 4x4), got {len(vals)}")
            M = np.array(t.floats(vals, key)).reshape(4, 4)
            cur[key] = M
            if key == "extrinsic" and cur.get("animated") and "intrinsic" in cur and "size" in cur:
                flush()
                cur["emitted"] = True
        elif key == "radial":
            if vals:
                cur["radial"] = t.to_float(vals[0], "radial coefficient")
        elif key in ("polynomial", "polynomialC2W", "polynomialW2C", "imageCircleRadius", "affine"):
            cur.setdefault("extra", {})[key] = vals  # fisheye model: kept out of the pinhole projection
        else:
            raise t.error(f"expected a calibration key (name, sensor, size, animated, intrinsic, extrinsic, radial), got '{key[:30]}'")
    if cur is not None and not cur.get("emitted"):
        flush()
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


