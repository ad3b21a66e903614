"""Which character, atlas and capture a shard set, a run or an avatar belongs to, and the refusal to mix them.

Shards record their character (``meta.h5`` ``character_sha256``: one sha256 over the template's source
files), runs record the identity of the shards they trained on (``train_config.json`` ``identity``)
and avatars carry it in their record. Every command that combines two of them (``eval RUN --shards``,
``train --resume``, ``render``/``view`` with shards) compares them here and refuses a mismatch with
an :class:`IdentityError` that names both sides.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from deliffas.data.shards import ShardSet, open_shard_set

__all__ = ["IdentityError", "capture_identity", "check_identity", "check_run_shards", "recorded_shards",
           "shards_record", "CHARACTER_KEYS", "CAPTURE_KEYS"]

CHARACTER_KEYS = ("character_sha256", "atlas_sha256")
"""The keys that must agree to render or evaluate a model on a shard set (same template, same atlas)."""
CAPTURE_KEYS = CHARACTER_KEYS + ("cameras_sha256",)
"""The keys that must agree to continue training on a shard set (also the same capture rig)."""


class IdentityError(ValueError):
    """Two things that must belong to the same character (or capture) do not; names both sides."""


def _digest(*arrays: np.ndarray, extra: str = "") -> str:
    h = hashlib.sha256(extra.encode())
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def capture_identity(meta) -> dict[str, str]:
    """The identity of a shard set's ``ShardMeta`` (or a run's capture record, also a ``ShardMeta``).

    Returns:
        ``character_sha256`` (the template's source files, as ``meta.h5`` records it), ``atlas_sha256``
        (faces, uvs, face_uvs and the atlas side) and ``cameras_sha256`` (names, intrinsics, poses, sizes).
    """
    character = meta.attrs.get("character_sha256") or _digest(np.asarray(meta.rest_verts, np.float64))
    atlas = _digest(np.asarray(meta.faces, np.int64), np.asarray(meta.uvs, np.float64),
                    np.asarray(meta.face_uvs, np.int64), extra=f"S={meta.atlas_res}")
    cameras = _digest(np.asarray(meta.K, np.float64), np.asarray(meta.world_to_cam, np.float64),
                      np.asarray(meta.sizes, np.int64), extra="|".join(meta.camera_names))
    return {"character_sha256": str(character), "atlas_sha256": atlas, "cameras_sha256": cameras}


def check_identity(expected: dict | None, expected_name: str, found: dict, found_name: str,
                   keys: tuple[str, ...] = CHARACTER_KEYS) -> None:
    """Refuse ``found`` when it differs from ``expected`` on any of ``keys``.

    ``expected`` None (a run written before identities were recorded) or a key missing on either side
    is not checked.

    Raises:
        IdentityError: naming both sides, the key and both short hashes.
    """
    if not expected:
        return
    what = {"character_sha256": "another character (template files)", "atlas_sha256": "another atlas",
            "cameras_sha256": "another capture (cameras)"}
    for key in keys:
        a, b = expected.get(key), found.get(key)
        if a is not None and b is not None and a != b:
            raise IdentityError(f"{found_name} is {what.get(key, key)} than {expected_name}: {key} "
                                f"{b[:12]}... there, {a[:12]}... in {expected_name}")


def shards_record(run: str | os.PathLike, shards: str | os.PathLike) -> dict[str, str]:
    """How a run records its shard set: the absolute path, and the path from the run folder (``shards``,
    ``shards_from_run``), so the shards are found from any working folder, and after the run and its
    shards moved together."""
    absolute = Path(shards).resolve()
    return {"shards": str(absolute), "shards_from_run": os.path.relpath(absolute, Path(run).resolve())}


def _candidates(run: str | os.PathLike, record: dict) -> list[Path]:
    train = record.get("train", {})
    found = [Path(train["shards"])] if train.get("shards") else []
    if train.get("shards_from_run"):
        found.append(Path(run) / train["shards_from_run"])
    elif found and not found[0].is_absolute():  # a run from before absolute paths: beside the run, too
        found.append(Path(run).parent / found[0])
    return found


def recorded_shards(run: str | os.PathLike, record: dict) -> str | None:
    """The shard set the run whose ``train_config.json`` is ``record`` trained on: its recorded path, else
    the same place seen from the run folder (moved together); None when neither holds a shard set."""
    for path in _candidates(run, record):
        if (path / "manifest.json").is_file():
            return str(path)
    return None


def check_run_shards(run: str | os.PathLike, record: dict, shards: ShardSet | str | os.PathLike | None) -> ShardSet:
    """Refuse ``shards`` for the run whose ``train_config.json`` is ``record``: gone, or another character.

    ``shards`` None means the run's own (:func:`recorded_shards`).

    Returns:
        The shard set, opened (``shards`` itself when it is one): the command passes it down.

    Raises:
        FileNotFoundError: no shard set there, naming every folder looked in and ``--shards``.
        IdentityError: the shards hold another character or atlas than the run was trained on.
    """
    if shards is None:
        shards = recorded_shards(run, record)
        if shards is None:
            looked = ", ".join(str(p.absolute()) for p in _candidates(run, record)) or "(none recorded)"
            raise FileNotFoundError(f"{run}: its shards are not where the run recorded them (looked in {looked}); "
                                    f"pass --shards DIR with the shards of {run}'s capture")
    elif not isinstance(shards, ShardSet) and not (Path(shards) / "manifest.json").is_file():
        raise FileNotFoundError(f"{Path(shards).absolute()}: no shard set there (no manifest.json); pass --shards "
                                f"DIR with the shards of {run}'s capture")
    shard_set = open_shard_set(shards)
    check_identity(record.get("identity"), f"the run {run}", capture_identity(shard_set.meta),
                   f"the shards {shard_set.out_dir}")
    return shard_set
