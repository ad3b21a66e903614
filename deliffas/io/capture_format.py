"""Checks shared by the capture-format readers, raising one error that names the file and the key.

Every reader of a capture dataset's files (EasyMocap, ZJU-MoCap, THuman4.0, DNA-Rendering,
ActorsHQ, nerfstudio) validates values through these functions, so a bad file always reads
``<file>: <key>: expected …, got …`` and never as a numpy broadcasting error three layers up.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from deliffas.io.cameras import ROTATION_TOLERANCE
from deliffas.io.files import durable_replace, temp_path

__all__ = [
    "CaptureFormatError", "require_array", "require_rotation", "require_size", "read_json",
    "write_json_atomic",
]



class CaptureFormatError(ValueError):
    """A capture-format file that does not match its format.

    The message reads ``<file>: <key>: <expectation>``; ``key`` is the file's own name for the
    entry (``K_cam01``, ``cams/R[3]``, ``Camera_Parameter/05/RT``, ``row 4: fx``, …).

    Attributes:
        path: the file at fault.
        key: the entry at fault, as the format names it.
        expectation: what was expected and what was found.
    """

    def __init__(self, path: str | os.PathLike, key: str, expectation: str):
        self.path = str(path)
        self.key = str(key)
        self.expectation = expectation
        super().__init__(f"{self.path}: {self.key}: {expectation}")


def require_array(path: str | os.PathLike, key: str, value: Any, shape: tuple[int, ...],
                  reshape: bool = False) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``.

    Args:
        path: named in the error.
        key: named in the error.
        value: anything numpy turns into a numeric array (nested lists, arrays, HDF5 datasets).
        shape: the expected shape; ``-1`` entries match any size.
        reshape: accept any array with the right number of elements (e.g. a flat list of 9 for a
            (3, 3) matrix, as readers that call ``np.reshape`` do), and reshape it row-major.

    Raises:
        CaptureFormatError: not numeric, wrong shape, or NaN/inf.
    """
    if value is None:
        raise CaptureFormatError(path, key, f"expected an array of shape {shape}, got nothing (missing)")
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureFormatError(path, key, f"expected numbers of shape {shape}, got {type(value).__name__}") from None
    if reshape and -1 not in shape and arr.size == int(np.prod(shape)):
        arr = arr.reshape(shape)
    if arr.ndim != len(shape) or any(s != -1 and s != a for s, a in zip(shape, arr.shape)):
        raise CaptureFormatError(path, key, f"expected shape {shape}, got {arr.shape}")
    bad = int((~np.isfinite(arr)).sum())
    if bad:
        raise CaptureFormatError(path, key, f"expected finite numbers, got {bad} NaN/inf of {arr.size}")
    return arr


def require_rotation(path: str | os.PathLike, key: str, R: Any) -> np.ndarray:
    """``R`` (3, 3) checked to be a rotation within ``ROTATION_TOLERANCE`` (orthonormal, det +1): the
    tolerance every ``Camera`` is held to, so a file accepted here makes a valid camera.

    Raises:
        CaptureFormatError: naming the deviation found (a mirrored R has det -1, a scaled one
            |R R^T - I| of the scale's square minus one).
    """
    R = require_array(path, key, R, (3, 3), reshape=True)
    orth = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if orth > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise CaptureFormatError(path, key, f"expected a rotation (R R^T = I and det R = +1 within {ROTATION_TOLERANCE:g}), "
                                            f"got max |R R^T - I| = {orth:.3g}, det R = {det:.9g}")
    return R


def require_size(path: str | os.PathLike, key: str, width: Any, height: Any) -> tuple[int, int]:
    """A positive integer image size (width, height).

    Raises:
        CaptureFormatError: non-integer or non-positive values.
    """
    try:
        w, h = float(width), float(height)
    except (TypeError, ValueError):
        raise CaptureFormatError(path, key, f"expected an integer image size, got {width!r} x {height!r}") from None
    if not (w.is_integer() and h.is_integer() and w > 0 and h > 0):
        raise CaptureFormatError(path, key, f"expected a positive integer image size, got {width!r} x {height!r}")
    return int(w), int(h)


def read_json(path: str | os.PathLike):
    """The parsed JSON of ``path``.

    Raises:
        CaptureFormatError: a missing file, non-UTF-8 bytes, or invalid (e.g. truncated) JSON, naming the line.
    """
    p = Path(path)
    if not p.is_file():
        raise CaptureFormatError(p, "file", "not found")
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise CaptureFormatError(p, "JSON", "expected UTF-8 JSON text, got binary bytes") from None
    except json.JSONDecodeError as err:
        raise CaptureFormatError(p, f"JSON line {err.lineno}", f"expected valid JSON ({err.msg})") from None


def write_json_atomic(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as JSON (floats at full precision, NaN refused) via a temporary file and an atomic rename."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(p)
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1, allow_nan=False)
    durable_replace(tmp, p)
