"""Sizing a training run by time (``TrainConfig.time_budget``): how many iterations fit, planned while it runs.

The first :data:`CALIBRATION` iterations lie inside the default 50-iteration warm-up, whose learning
rate does not depend on the run's length: the run times them (all but the first :data:`UNTIMED`, which
pay for the start-up) and plans its length from their speed. It plans again, at the speed of the
iterations since the last plan, once half of what is left is done, while more than :data:`MIN_LEFT`
iterations are left and at most :data:`MAX_PLANS` times in all: a machine that slows down (or speeds up)
after the first iterations still ends the run near its budget. Each plan keeps :data:`MARGIN` of the
time left for checkpoints, previews and drift.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = ["CALIBRATION", "UNTIMED", "MARGIN", "MIN_LEFT", "MAX_PLANS", "budgeted_iters", "BudgetPlanner"]

CALIBRATION = 40
"""Iterations timed before the first plan (from the run's start or resumed iteration)."""
UNTIMED = 10
"""The first iterations of the run, not timed (start-up: the data stream's first reads, allocations)."""
MARGIN = 0.97
"""Fraction of the time left that a plan fills."""
MIN_LEFT = 200
"""A plan leaving fewer iterations than twice this is the last."""
MAX_PLANS = 5
"""Plans of one run at most."""


def budgeted_iters(done: int, seconds_per_iteration: float, seconds_left: float) -> int:
    """The run's length at iteration ``done``: ``done`` plus the iterations that fit in :data:`MARGIN` x
    ``seconds_left`` at ``seconds_per_iteration`` (never fewer than ``done``)."""
    if not seconds_per_iteration > 0:
        raise ValueError(f"seconds_per_iteration: expected > 0, got {seconds_per_iteration!r}")
    return done + max(0, int(MARGIN * seconds_left / seconds_per_iteration))


@dataclass
class BudgetPlanner:
    """Plans the length of one run of ``seconds`` that started (its trainer was made) at ``created``
    (``time.perf_counter``) and trains from iteration ``start``. Call :meth:`after` after every iteration."""

    seconds: float
    created: float
    start: int
    next_plan: int | None = None
    mark: tuple[int, float] | None = None
    plans: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.next_plan = self.start + CALIBRATION

    def after(self, done: int, now: float, agree: Callable[[int], int] | None = None) -> int | None:
        """``done`` iterations are finished at ``now``: the run's new length when it plans now, else None.

        ``agree`` turns this process's plan into the one every process follows (under DDP: rank 0's); the
        next plan's iteration is derived from it, so every process plans again at the same iteration."""
        if done == self.start + UNTIMED:
            self.mark = (done, now)
        if done != self.next_plan or self.mark is None:
            return None
        per_it = (now - self.mark[1]) / (done - self.mark[0])
        iters = budgeted_iters(done, per_it, self.seconds - (now - self.created))
        if agree is not None:
            iters = agree(iters)
        self.plans.append({"at_iteration": done, "seconds_per_iteration": per_it, "iterations": iters})
        half = (iters - done) // 2
        self.next_plan = done + half if half >= MIN_LEFT and len(self.plans) < MAX_PLANS else None
        self.mark = (done, now)
        return iters

    def record(self) -> dict:
        """What ``train_config.json`` keeps of the sizing: the budget, the length and every plan."""
        return {"seconds": self.seconds, "iterations": self.plans[-1]["iterations"] if self.plans else None,
                "plans": self.plans}
