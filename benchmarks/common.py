"""The result record and timing helper shared by every benchmark module."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

SAMPLE_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "dynacap-sample"


@dataclass
class Result:
    """One benchmark line.

    Attributes:
        name: what was measured.
        value: the measurement in ``unit``.
        ratio: value relative to the same-run baseline named in ``baseline`` (None if none).
        target: the goal as text, e.g. ">= 5x" (empty when informational).
        passed: whether the target was met (None when informational).
    """

    group: str
    name: str
    value: float
    unit: str
    baseline: str = ""
    ratio: float | None = None
    target: str = ""
    passed: bool | None = None
    note: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


def best_time(fn: Callable[[], object], repeat: int = 3, min_time: float = 0.0) -> float:
    """Best wall time of ``fn`` over ``repeat`` runs (after one warm-up call), seconds."""
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
