"""What a command interrupted by Ctrl-C kept, and the exact command that continues it.

Stdlib only: the interrupt may have arrived while torch or h5py were being imported, and importing a
half-initialised extension module again crashes the process; so the two records are read as plain JSON
(``manifest.json`` of docs/shards.md, ``train_state.json`` of ``engine.checkpointing``).
"""

from __future__ import annotations

import argparse
import io
import json
import shlex
import signal
import sys
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

__all__ = ["interrupted_line", "resume_command", "report_interrupted"]


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
    """``: <what is kept>; resume with: <command>`` for ``convert``, ``ingest`` and ``train``, else empty."""
    if args.command == "convert":
        m = _json(Path(args.out) / "manifest.json")
        shards, planned = m.get("shards"), m.get("planned")
        kept = (f"{len(shards)} of {len(planned)} shards kept in {args.out}"
                if isinstance(shards, list) and isinstance(planned, list) and planned else "no shard finished yet")
        return f": {kept}; resume with: {resume_command(argv)}"
    if args.command == "ingest":
        work = Path(args.out) / ".ingest"
        kept = sorted(p.stem for p in work.glob("*.npz")) if work.is_dir() else []
        return (f": {', '.join(kept) if kept else 'no stage finished yet'} kept in {work}; resume with: "
                f"{resume_command(argv)}")
    if args.command == "train" and not getattr(args, "auto_capacity", False):
        done = _json(Path(args.out) / "train_state.json").get("iteration")
        kept = f"checkpoint at iteration {done} kept in {args.out}" if isinstance(done, int) else "no checkpoint yet"
        return f": {kept}; resume with: {shlex.join(['deliffas', 'train', '--resume', '--out', str(args.out)])}"
    return ""


def report_interrupted(args: argparse.Namespace | None, argv: list[str]) -> int:
    """Print the one line of a command that Ctrl-C interrupted and return its exit code, 130.

    ``args`` None: interrupted before its arguments were parsed; they are parsed here (quietly). Arguments the
    parser refuses give a line that names no command.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C while the state is reported: no traceback
    if args is None:
        from deliffas.cli import build_parser  # local: import cycle (deliffas.cli imports this module)

        try:
            with redirect_stdout(io.StringIO()), redirect_stderr(io.StringIO()):
                args = build_parser().parse_args(argv)
        except SystemExit:  # refused, or --help
            print("deliffas: interrupted", file=sys.stderr)
            return 130
    print(f"deliffas {args.command}: interrupted{interrupted_line(args, argv)}", file=sys.stderr)
    return 130
