"""The result record, the timing helper and the smoke-mode switch shared by every benchmark module."""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, TypeVar

SAMPLE_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "dynacap-sample"
SMOKE_ENV = "DELIFFAS_BENCH_SMOKE"
"""Environment variable of the smoke mode (``python -m benchmarks.run --smoke`` sets it to 1, and the probes the
modules start in fresh processes inherit it): every module runs its code paths at tiny sizes with one timed
repetition, and the runner judges no target."""

T = TypeVar("T")


def smoke() -> bool:
    """Whether the benchmarks run in smoke mode (:data:`SMOKE_ENV` set and not "0")."""
    return os.environ.get(SMOKE_ENV, "") not in ("", "0")


def sized(full: T, tiny: T) -> T:
    """``tiny`` in smoke mode, else ``full``: a module's choice of sizes, counts or repetitions."""
    return tiny if smoke() else full


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
    """Best wall time of ``fn`` over ``repeat`` runs (after one warm-up call), seconds; one run in smoke mode."""
    repeat = sized(repeat, 1)
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
