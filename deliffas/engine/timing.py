"""Per-stage wall-clock timing (the paper's runtime breakdown: uv, cnn, sample, mlp)."""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

import torch

__all__ = ["StageTimer", "STAGES"]

STAGES = ("uv", "cnn", "sample", "mlp")


class StageTimer:
    """Accumulates milliseconds per named stage; synchronises CUDA so GPU time is counted."""

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.total_ms: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextmanager
    def stage(self, name: str):
        self._sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._sync()
            self.total_ms[name] += (time.perf_counter() - t0) * 1000
            self.counts[name] += 1

    def per_unit(self, units: int) -> dict[str, float]:
        """Milliseconds per unit (e.g. per rendered image) for every stage seen (0 for the rest)."""
        units = max(units, 1)
        out = {s: self.total_ms.get(s, 0.0) / units for s in STAGES}
        out.update({k: v / units for k, v in self.total_ms.items() if k not in STAGES})
        return out
