"""What ``verify_conversion`` checks (:class:`VerifyConfig`) and what it finds (:class:`ShardVerification`); light,
so the CLI reads it without h5py."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from deliffas.options import opt

__all__ = ["ShardVerification", "VerifyConfig"]


@dataclass(frozen=True)
class VerifyConfig:
    """A converted folder checked against its manifest (:func:`deliffas.data.shards.verify_conversion`)."""

    out: Path = opt(help="folder written by 'deliffas convert'", flag="")
    quick: bool = opt(False, help="sizes and sha256s only; without it every dataset of every shard is also read once")
    json: bool = opt(False, help="print the result as one JSON object (out, deep, shards, ok, problems)")


@dataclass(frozen=True)
class ShardVerification:
    """An output folder checked against its manifest (:func:`deliffas.data.shards.verify_shards`)."""

    out: Path
    deep: bool
    """Every dataset of every shard was also read once (not ``--quick``)."""
    shards: int
    """Complete shards the manifest lists (0 when it cannot be read)."""
    problems: tuple[str, ...]
    """One message per problem, each naming its file (docs/shards.md lists them)."""

    @property
    def ok(self) -> bool:
        """No problem found."""
        return not self.problems

    def to_json(self) -> dict:
        return {"out": str(self.out), "deep": self.deep, "shards": self.shards, "ok": self.ok,
                "problems": list(self.problems)}
