"""What a command interrupted by Ctrl-C kept, and the exact command that continues it.

Stdlib only: the interrupt may have arrived while torch or h5py were being imported, and importing a
half-initialised extension module again crashes the process; so the two records are read as plain JSON
(``manifest.json`` of docs/shards.md, ``train_state.json`` of ``engine.checkpointing``).
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

__all__ = ["interrupted_line", "resume_command"]


def resume_command(argv: list[str]) -> str:
    """``argv`` as the command that resumes it: ``--resume`` added, ``--overwrite`` dropped (it would start over)."""
    kept = [a for a in argv if a != "--overwrite"]
    return shlex.join(["deliffas", *kept, *([] if "--resume" in kept else ["--resume"])])


def _json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def interrupted_line(args: argparse.Namespace, argv: list[str]) -> str:
    """``: <what is kept>; resume with: <command>`` for ``convert`` and ``train``, else empty."""
    if args.command == "convert":
        m = _json(Path(args.out) / "manifest.json")
        shards, planned = m.get("shards"), m.get("planned")
        kept = (f"{len(shards)} of {len(planned)} shards kept in {args.out}"
                if isinstance(shards, list) and isinstance(planned, list) and planned else "no shard finished yet")
        return f": {kept}; resume with: {resume_command(argv)}"
    if args.command == "train" and not getattr(args, "auto_capacity", False):
        done = _json(Path(args.out) / "train_state.json").get("iteration")
        kept = f"checkpoint at iteration {done} kept in {args.out}" if isinstance(done, int) else "no checkpoint yet"
        return f": {kept}; resume with: {shlex.join(['deliffas', 'train', '--resume', '--out', str(args.out)])}"
    return ""
