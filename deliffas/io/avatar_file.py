"""The ``.avatar`` file format: named arrays and one JSON record in a safetensors file, every array checksummed.

An avatar file is what ``deliffas export`` writes and ``render``/``view``/the Python API load: plain
arrays (model weights, atlas, faces, cameras, the template's source files as uint8 bytes) plus a JSON
record (configs, template spec, identity). Layout (safetensors, no pickle anywhere)::

    tensors:   <name> -> array (float32/float64/int32/int64/uint8/bool)
    metadata:  "format" = "deliffas-avatar", "version" = "1",
               "record" = JSON object, "sha256" = JSON {name: sha256 of dtype, shape and bytes}

The same format holds a run's capture record (``RUN/capture.avatar``: everything but the weights).
Writes are atomic (temporary name, fsync, rename); reading checks format, version, JSON and every
array's sha256 and raises :class:`AvatarFileError` naming the file and what was wrong.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from deliffas.checks import finite_as
from deliffas.io.infra.files import write_bytes_atomic

__all__ = ["AvatarFile", "AvatarFileError", "write_avatar_file", "read_avatar_file", "AVATAR_FORMAT",
           "AVATAR_VERSION", "AVATAR_SUFFIX"]

AVATAR_FORMAT = "deliffas-avatar"
"""``metadata["format"]`` of every avatar file."""
AVATAR_VERSION = 1
"""Layout version; a reader refuses any other."""
AVATAR_SUFFIX = ".avatar"
"""The suffix ``deliffas export`` writes and ``deliffas zoo list DIR`` looks for."""


class AvatarFileError(ValueError):
    """An avatar file that is missing, truncated, corrupted or of another format (names the file)."""


@dataclass(frozen=True)
class AvatarFile:
    """The contents of an avatar file."""

    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    """Name -> array, exactly as written (each verified against its recorded sha256)."""
    record: dict = field(default_factory=dict)
    """The JSON record (configs, template spec, identity, ...)."""


def _array_sha256(a: np.ndarray) -> str:
    h = hashlib.sha256(f"{a.dtype.str}|{','.join(map(str, a.shape))}|".encode())
    h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def write_avatar_file(path: str | os.PathLike, arrays: dict[str, np.ndarray], record: dict) -> Path:
    """Write ``arrays`` and ``record`` (JSON-serialisable) to ``path`` atomically; returns the path.

    Raises:
        ValueError: ``record`` is not JSON-serialisable, an array name is not a string, or a float array
            holds NaN or inf.
    """
    from safetensors.numpy import save as safetensors_save

    out = Path(path)
    clean = {str(k): np.ascontiguousarray(v) for k, v in arrays.items()}
    for name, a in clean.items():  # NaN weights render as corrupted pixels with exit 0: never written
        finite_as(f"{out}: array {name!r}", a, a.dtype)
    try:
        record_json = json.dumps(record, sort_keys=True)
    except TypeError as exc:
        raise ValueError(f"{out}: the avatar record is not JSON-serialisable ({exc})") from exc
    metadata = {"format": AVATAR_FORMAT, "version": str(AVATAR_VERSION), "record": record_json,
                "sha256": json.dumps({k: _array_sha256(v) for k, v in sorted(clean.items())}, sort_keys=True)}
    blob = safetensors_save(clean, metadata=metadata)
    out.parent.mkdir(parents=True, exist_ok=True)
    return write_bytes_atomic(out, blob)


def _json_object(path: Path, metadata: dict, key: str) -> dict:
    try:
        value = json.loads(metadata[key])
    except KeyError:
        raise AvatarFileError(f"{path}: metadata has no {key!r} (not a deliffas avatar file?)") from None
    except (json.JSONDecodeError, TypeError) as exc:
        raise AvatarFileError(f"{path}: metadata {key!r} is not JSON ({exc})") from None
    if not isinstance(value, dict):
        raise AvatarFileError(f"{path}: metadata {key!r}: expected a JSON object, got {type(value).__name__}")
    return value


def read_avatar_file(path: str | os.PathLike) -> AvatarFile:
    """Read and verify an avatar file.

    Raises:
        AvatarFileError: missing file, not safetensors (or truncated), another format or version, bad JSON,
            an array missing, extra or whose bytes differ from its recorded sha256, or a float array holding NaN
            or inf (each named).
    """
    from safetensors.numpy import load as safetensors_load

    p = Path(path)
    if not p.is_file():
        raise AvatarFileError(f"{p}: missing (expected a {AVATAR_SUFFIX} file written by 'deliffas export')")
    blob = p.read_bytes()
    try:
        arrays = safetensors_load(blob)
        header_len = int.from_bytes(blob[:8], "little")  # the layout safetensors_load just validated
        metadata = json.loads(blob[8:8 + header_len]).get("__metadata__") or {}
    except Exception as exc:  # noqa: BLE001 - safetensors raises its own error types for broken headers
        raise AvatarFileError(f"{p}: not a readable safetensors file (truncated or corrupted? {exc})") from None
    if metadata.get("format") != AVATAR_FORMAT:
        raise AvatarFileError(f"{p}: expected format {AVATAR_FORMAT!r}, got {metadata.get('format')!r}")
    if metadata.get("version") != str(AVATAR_VERSION):
        raise AvatarFileError(f"{p}: expected version {AVATAR_VERSION}, got {metadata.get('version')!r}")
    record = _json_object(p, metadata, "record")
    sums = _json_object(p, metadata, "sha256")
    if set(sums) != set(arrays):
        missing, extra = sorted(set(sums) - set(arrays)), sorted(set(arrays) - set(sums))
        raise AvatarFileError(f"{p}: arrays differ from the recorded list (missing {missing[:5]}, extra {extra[:5]})")
    for name, array in arrays.items():
        if _array_sha256(array) != sums[name]:
            raise AvatarFileError(f"{p}: array {name!r} is corrupted (sha256 differs from the recorded one)")
        if array.dtype.kind == "f" and not np.isfinite(array).all():  # e.g. a buggy export: valid sha256, NaN weights
            bad = int((~np.isfinite(array)).sum())
            raise AvatarFileError(f"{p}: array {name!r} holds {bad} NaN/inf of {array.size} values (expected finite "
                                  "numbers; export the run again from a finite checkpoint)")
    return AvatarFile(arrays, record)
