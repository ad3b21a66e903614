"""Shared constants and helpers of the reliability suite (imported by name: pytest puts this folder on sys.path).

``COUNTS`` collects what the suite exercised (kills survived, cases fuzzed, ...); ``conftest.py``
prints the totals at the end of the run so the CI log shows them (docs/reliability.md quotes one run).
"""

from __future__ import annotations

import hashlib
import os
from collections import Counter
from pathlib import Path

CAPTURE = dict(num_frames=12, num_test_frames=2, num_cameras=4, width=48, height=48, seed=1)
"""SynthConfig fields of the session capture."""
CONVERT_ARGS = ("--shard-frames", "2", "--atlas-res", "32")
"""CLI options of every conversion in the suite (7 shards of the session capture)."""
CONVERT_KW = dict(shard_frames=2, atlas_res=32)
"""The same as ``ConvertConfig`` fields."""

SOAK = os.environ.get("DELIFFAS_SOAK", "") not in ("", "0")
"""``make soak`` (``DELIFFAS_SOAK=1``): the same tests at soak scale (>= 10,000 fuzz cases per reader,
>= 20 SIGKILLs of conversion); unset in CI, which keeps the small counts."""
FUZZ_EXAMPLES = int(os.environ.get("DELIFFAS_FUZZ_EXAMPLES", "10000" if SOAK else "150"))
"""Hypothesis examples per fuzzed reader (``DELIFFAS_FUZZ_EXAMPLES`` overrides)."""
KILL_ROUNDS = int(os.environ.get("DELIFFAS_KILL_ROUNDS", "4" if SOAK else "1"))
"""Rounds of the seeded conversion kill chains (6 SIGKILLs each: 5 with --jobs 1 and --resume, 1 with --jobs 2)."""

COUNTS: Counter = Counter()
"""What the suite exercised in this run."""


def tree_state(root: Path) -> dict[str, tuple]:
    """Every file and folder under ``root``: relative path -> (kind, size, mtime_ns, sha256)."""
    state = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for d in dirnames:
            p = Path(dirpath) / d
            st = p.stat()
            state[str(p.relative_to(root)) + "/"] = ("dir", None, st.st_mtime_ns, None)
        for f in filenames:
            p = Path(dirpath) / f
            st = p.stat()
            state[str(p.relative_to(root))] = ("file", st.st_size, st.st_mtime_ns,
                                               hashlib.sha256(p.read_bytes()).hexdigest())
    return state
