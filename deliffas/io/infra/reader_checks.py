"""Checks shared by the capture-format readers, raising one error that names the file and the key.

Every reader of a capture dataset's files (EasyMocap, ZJU-MoCap, THuman4.0, DNA-Rendering,
ActorsHQ, nerfstudio, COLMAP; AMASS motions and SMPL models read their ``.npz`` through ``read_npz``)
validates values through these functions, so a bad file always reads
``<file>: <key>: expected …, got …`` and never as a numpy broadcasting error three layers up.
"""

from __future__ import annotations

import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from deliffas.io.cameras import ROTATION_TOLERANCE, check_camera_names
from deliffas.io.infra.files import durable_replace, temp_path

__all__ = [
    "CaptureFormatError", "require_numbers", "require_array", "require_rows", "require_vector", "require_rotation",
    "require_size", "read_json", "read_npz", "write_json_atomic", "naming_file",
    "require_unique_names",
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


@contextmanager
def naming_file(path: str | os.PathLike, key: str):
    """Re-raise a ValueError of building a record from ``path`` (e.g. a ``Camera`` refusing a singular K or a
    translation that overflows to inf in millimetres) as a ``CaptureFormatError`` naming the file and ``key``."""
    try:
        yield
    except CaptureFormatError:
        raise
    except ValueError as err:
        raise CaptureFormatError(path, key, str(err)) from None


def require_numbers(path: str | os.PathLike, key: str, value: Any, what: str = "") -> np.ndarray:
    """``value`` as a float64 array of any shape, from real numbers only: text, booleans, complex numbers,
    nested objects, ragged lists and integers beyond float64 are refused rather than converted.

    Raises:
        CaptureFormatError: naming ``what`` was expected (e.g. " of shape (3, 3)") and what was found.
    """
    try:
        raw = np.asarray(value)
        if raw.dtype.kind == "O" and all(isinstance(x, (int, float, np.integer, np.floating))
                                         and not isinstance(x, (bool, np.bool_)) for x in raw.flat):
            return raw.astype(np.float64)  # e.g. JSON integers too large for int64
        if raw.dtype.kind in "iuf":
            return raw.astype(np.float64)
        found = f"{raw.dtype} values" if raw.dtype.kind != "O" else f"{type(value).__name__} holding non-numbers"
    except (TypeError, ValueError, OverflowError) as err:  # ragged lists; integers beyond float64
        found = f"{type(value).__name__} ({str(err).splitlines()[0][:80]})"
    raise CaptureFormatError(path, key, f"expected real numbers{what}, got {found}")


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
    arr = require_numbers(path, key, value, f" of shape {shape}")
    if reshape and -1 not in shape and arr.size == int(np.prod(shape)):
        arr = arr.reshape(shape)
    if arr.ndim != len(shape) or any(s != -1 and s != a for s, a in zip(shape, arr.shape)):
        raise CaptureFormatError(path, key, f"expected shape {shape}, got {arr.shape}")
    bad = int((~np.isfinite(arr)).sum())
    if bad:
        raise CaptureFormatError(path, key, f"expected finite numbers, got {bad} NaN/inf of {arr.size}")
    return arr


def require_rows(path: str | os.PathLike, key: str, value: Any, rows: int = -1) -> np.ndarray:
    """``value`` as a finite (rows, N) float64 array, a 1-D value taken as one row (``np.atleast_2d``), as the
    SMPL records store (1, 72) poses and (10,) or (1, 10) betas."""
    if value is None:
        raise CaptureFormatError(path, key, "expected an array, got nothing (missing)")
    return require_array(path, key, np.atleast_2d(require_numbers(path, key, value)), (rows, -1))


def require_vector(path: str | os.PathLike, key: str, value: Any) -> np.ndarray:
    """``value`` flattened to a finite 1-D float64 array (distortion stored as (5,), (1, 5) or (5, 1))."""
    if value is None:
        raise CaptureFormatError(path, key, "expected an array, got nothing (missing)")
    return require_array(path, key, require_numbers(path, key, value).ravel(), (-1,))


def require_rotation(path: str | os.PathLike, key: str, R: Any) -> np.ndarray:
    """``R`` (3, 3) checked to be a rotation within ``ROTATION_TOLERANCE`` (orthonormal, det +1): the
    tolerance every ``Camera`` is held to, so a file accepted here makes a valid camera.

    Raises:
        CaptureFormatError: naming the deviation found (a mirrored R has det -1, a scaled one
            |R R^T - I| of the scale's square minus one).
    """
    R = require_array(path, key, R, (3, 3), reshape=True)
    with np.errstate(over="ignore", invalid="ignore"):  # a huge R overflows to inf/NaN, which fails the check below
        orth = float(np.abs(R @ R.T - np.eye(3)).max())
        det = float(np.linalg.det(R))
    if not (orth <= ROTATION_TOLERANCE and abs(det - 1.0) <= ROTATION_TOLERANCE):
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
    except (TypeError, ValueError, OverflowError):
        raise CaptureFormatError(path, key, f"expected an integer image size, got {width!r} x {height!r}") from None
    if not (w.is_integer() and h.is_integer() and w > 0 and h > 0):
        raise CaptureFormatError(path, key, f"expected a positive integer image size, got {width!r} x {height!r}")
    return int(w), int(h)


def require_unique_names(path: str | os.PathLike, key: str, names: Sequence[str]) -> list[str]:
    """``names`` (camera names), refused when one is given twice (``check_camera_names``).

    Raises:
        CaptureFormatError: naming the file, ``key`` and the repeated name.
    """
    with naming_file(path, key):
        check_camera_names(names)
    return [str(n) for n in names]


def read_json(path: str | os.PathLike):
    """The parsed JSON of ``path``.

    Raises:
        CaptureFormatError: a missing file, non-UTF-8 bytes, invalid (e.g. truncated) JSON, naming the line, or
            a key given twice in one object.
    """
    p = Path(path)
    if not p.is_file():
        raise CaptureFormatError(p, "file", "not found")

    def unique_keys(pairs: list[tuple[str, Any]]) -> dict:
        out: dict = {}
        for key, value in pairs:
            if key in out:  # json.loads would keep the last silently (a second camera replacing the first)
                raise CaptureFormatError(p, f"JSON key {key!r}", "given twice in one object (expected unique keys)")
            out[key] = value
        return out

    try:
        return json.loads(p.read_text(encoding="utf-8"), object_pairs_hook=unique_keys)
    except UnicodeDecodeError:
        raise CaptureFormatError(p, "JSON", "expected UTF-8 JSON text, got binary bytes") from None
    except json.JSONDecodeError as err:
        raise CaptureFormatError(p, f"JSON line {err.lineno}", f"expected valid JSON ({err.msg})") from None


def read_npz(path: str | os.PathLike, text_keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Every member of the ``.npz`` archive ``path`` as an array, never unpickling.

    Each member's ``.npy`` header is checked before its data is read: a shape whose bytes exceed what
    the member holds is refused instead of allocated. Members must hold real numbers (bool, int, uint,
    float); members named in ``text_keys`` may also hold text, and are left out when pickled.

    Raises:
        CaptureFormatError: a missing file, not a zip archive, or a damaged, truncated, pickled or
            non-numeric member (the key is the member's name).
    """
    import zipfile
    from numpy.lib import format as npy

    p = Path(path)
    if not p.is_file():
        raise CaptureFormatError(p, "file", "not found")
    try:
        archive = zipfile.ZipFile(p)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as err:
        # (NotImplementedError: a damaged "version needed to extract" field)
        raise CaptureFormatError(p, "NPZ", f"expected an .npz (zip) archive ({err})") from None
    out = {}
    with archive:
        for info in archive.infolist():
            key = (info.filename[:-4] if info.filename.endswith(".npy") else info.filename) or "(a member without a name)"
            try:
                with archive.open(info) as fh:
                    version = npy.read_magic(fh)
                    if version not in ((1, 0), (2, 0)):
                        raise ValueError(f"unsupported .npy format version {version}")
                    read_header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
                    shape, fortran, dtype = read_header(fh)
                    if dtype.kind == "O" and key in text_keys:
                        continue  # a pickled text entry: left out rather than unpickled
                    kinds = "biufSU" if key in text_keys else "biuf"
                    if dtype.kind not in kinds or dtype.itemsize == 0 or dtype.fields is not None:
                        raise CaptureFormatError(p, key, f"expected an array of real numbers, got dtype {dtype}")
                    count = int(np.prod(shape, dtype=object))
                    if count * dtype.itemsize > info.file_size:
                        raise CaptureFormatError(p, key, f"shape {shape} of {dtype} needs {count * dtype.itemsize} "
                                                         f"bytes, the member holds {info.file_size}")
                    data = fh.read(count * dtype.itemsize)
                    if len(data) != count * dtype.itemsize:
                        raise CaptureFormatError(p, key, f"truncated: {len(data)} of {count * dtype.itemsize} bytes")
                    arr = np.frombuffer(data, dtype, count).reshape(shape, order="F" if fortran else "C").copy()
            except CaptureFormatError:
                raise
            except Exception as err:  # zipfile, zlib and numpy's header parser fail in many ways on damaged bytes
                raise CaptureFormatError(p, key, f"unreadable .npz member ({type(err).__name__}: "
                                                 f"{str(err)[:200]})") from None
            out[key] = arr
    return out


def write_json_atomic(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as JSON (floats at full precision, NaN refused) via a temporary file and an atomic rename."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(p)
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1, allow_nan=False)
    durable_replace(tmp, p)
