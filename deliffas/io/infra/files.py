"""Files on disk: their identity (sha256, recorded by manifests, runs and template specs) and atomic replacement.

Every writer in deliffas writes under :func:`temp_path` next to the final name and renames it into
place (:func:`atomic_path` does both and cleans up after a failure), so a crash never leaves a half-written file under a final name; ``.<name>.tmp-<pid>`` files
left by a crash are recognisable (``TMP_MARK``) and removed by the next run.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["sha256_file", "temp_path", "durable_replace", "atomic_path", "write_bytes_atomic", "claim_output",
           "claim_output_file", "check_writable", "TMP_MARK"]

TMP_MARK = ".tmp-"
"""Part of every temporary file name (``.<name>.tmp-<pid>``)."""


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 22) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            block = fh.read(chunk)
            if not block:
                return h.hexdigest()
            h.update(block)


def temp_path(path: str | os.PathLike, keep_suffix: bool = False) -> Path:
    """The temporary name a file is written under before its atomic rename: ``.<name>.tmp-<pid>``
    (``.<stem>.tmp-<pid><suffix>`` with ``keep_suffix``, for writers that choose a format by suffix)."""
    p = Path(path)
    if keep_suffix:
        return p.with_name(f".{p.stem}{TMP_MARK}{os.getpid()}{p.suffix}")
    return p.with_name(f".{p.name}{TMP_MARK}{os.getpid()}")


def durable_replace(tmp: str | os.PathLike, final: str | os.PathLike) -> None:
    """fsync ``tmp`` and rename it to ``final`` (atomic on POSIX within one file system)."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, final)


@contextmanager
def atomic_path(path: str | os.PathLike, keep_suffix: bool = False) -> Iterator[Path]:
    """Yield the :func:`temp_path` to write ``path`` under; when the block ends normally, fsync it and rename it
    to ``path`` (:func:`durable_replace`); whatever happens, no temporary file is left behind.

    Example: ``with atomic_path(out) as tmp: tmp.write_bytes(data)``.
    """
    p = Path(path)
    tmp = temp_path(p, keep_suffix)
    try:
        yield tmp
        durable_replace(tmp, p)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` under :func:`temp_path`, fsync and rename it to ``path`` (no partial file on a crash)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def claim_output(path: str | os.PathLike, overwrite: bool, marker: str, what: str) -> Path:
    """Make ``path`` ready to be written as a folder by a command, never replacing a user's work unasked.

    A missing or empty folder is created. A non-empty one is refused unless ``overwrite``; with it, it is
    removed first only when it holds ``marker`` (the file the command writes last, so the folder is
    recognisably its own output), and refused otherwise: deliffas never deletes a folder it did not write.

    Raises:
        FileExistsError: naming the folder and what to do.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise FileExistsError(f"{p}: exists and is not a folder")
    if p.is_dir() and any(p.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{p}: not empty; pass --overwrite to replace {what} there")
        if not (p / marker).is_file():
            raise FileExistsError(f"{p}: not empty and not {what} (no {marker}); deliffas only replaces its own "
                                  "output: remove or empty the folder yourself")
        shutil.rmtree(p)
    p.mkdir(parents=True, exist_ok=True)
    return p


def claim_output_file(path: str | os.PathLike, overwrite: bool) -> Path:
    """Refuse to replace an existing file unless ``overwrite`` (the write itself stays atomic)."""
    p = Path(path)
    if p.exists() and not overwrite:
        raise FileExistsError(f"{p}: exists; pass --overwrite to replace it")
    if p.is_dir():
        raise FileExistsError(f"{p}: is a folder, expected a file name")
    return check_writable(p)


def check_writable(path: str | os.PathLike, folder: bool = False) -> Path:
    """Make sure ``path`` (a file; with ``folder``, a folder) can be written, before any work is done: its
    folder is created and a temporary file is written there and removed.

    Raises:
        PermissionError: naming the path, the reason and what to do.
    """
    p = Path(path)
    where = p if folder else p.parent
    probe = temp_path(where / ".deliffas-write-probe")
    try:
        where.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise PermissionError(f"{p}: cannot write there ({err.strerror or err}); choose another path") from None
    return p
