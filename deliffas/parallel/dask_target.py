"""The ``--dask`` value: a running scheduler's address or ``local:N`` (a LocalCluster of N workers).

Parsing only (no dask import), so the CLI can check the value before any work starts.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["DaskTarget", "parse_dask_target"]

_ADDRESS = re.compile(r"^(?:(tcp|tls|ws|wss|inproc)://)?[A-Za-z0-9_.\-\[\]:]+:\d{1,5}$")


@dataclass(frozen=True)
class DaskTarget:
    """Where Dask tasks run."""

    address: str | None
    """A running scheduler, e.g. ``tcp://10.0.0.5:8786``; None = a LocalCluster started here."""
    local_workers: int = 0
    """Worker processes of the LocalCluster (``local:N``); 0 with an address."""


def parse_dask_target(text: str) -> DaskTarget:
    """``local:N`` (N >= 1) or a scheduler address ``[tcp://]HOST:PORT``; ValueError otherwise."""
    text = text.strip()
    if text.startswith("local:"):
        count = text[len("local:"):]
        if not count.isdigit() or int(count) < 1:
            raise ValueError(f"--dask local:N needs a worker count N >= 1, got {text!r}")
        return DaskTarget(None, int(count))
    if not _ADDRESS.match(text):
        raise ValueError(f"--dask expects a scheduler address such as tcp://HOST:8786 or local:N, got {text!r}")
    return DaskTarget(text if "://" in text else f"tcp://{text}")
