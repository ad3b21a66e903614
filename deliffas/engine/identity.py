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

__all__ = ["IdentityError", "capture_identity", "check_identity", "check_run_shards", "CHARACTER_KEYS",
           "CAPTURE_KEYS"]

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


def check_run_shards(run: str | os.PathLike, record: dict, shards: ShardSet | str | os.PathLike) -> ShardSet:
    """Refuse ``shards`` for the run whose ``train_config.json`` is ``record``: gone, or another character.

    Returns:
        The shard set, opened (``shards`` itself when it is one): the command passes it down.

    Raises:
        FileNotFoundError: no shard set at ``shards`` (says to pass ``--shards``).
        IdentityError: the shards hold another character or atlas than the run was trained on.
    """
    if not isinstance(shards, ShardSet) and not (Path(shards) / "manifest.json").is_file():
        raise FileNotFoundError(f"{shards}: no shard set there (moved or deleted?); pass --shards DIR with the "
                                f"shards of {run}'s capture")
    shard_set = open_shard_set(shards)
    check_identity(record.get("identity"), f"the run {run}", capture_identity(shard_set.meta),
                   f"the shards {shard_set.out_dir}")
    return shard_set
