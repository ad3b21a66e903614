"""What ``verify_conversion`` checks (:class:`VerifyConfig`); light, so the CLI reads it without h5py."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from deliffas.options import opt

__all__ = ["VerifyConfig"]


@dataclass(frozen=True)
class VerifyConfig:
    """A converted folder checked against its manifest (:func:`deliffas.data.shards.verify_conversion`)."""

    out: Path = opt(help="folder written by 'deliffas convert'", flag="")
    quick: bool = opt(False, help="checksums only, do not read every dataset")
    """Sizes and sha256s only; otherwise every dataset of every shard is also read once."""
