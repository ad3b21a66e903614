"""Interleaved best-of timing for same-run ratios on a shared, noisy machine."""

from __future__ import annotations

import contextlib
import time
from typing import Callable, Iterator

from benchmarks.common import smoke


def best_times(fns: dict[str, Callable[[], object]], repeat: int = 5, min_time: float = 0.0,
               max_rounds: int | None = None) -> dict[str, float]:
    """Best wall time (s) of each function, calling them in turn (a, b, a, b, ...) after one warm-up each.

    Interleaving exposes every candidate to the same load of the machine, so the ratio of two
    best times is not skewed by a burst of other work during one of them. Runs ``repeat``
    rounds, and more while the total time of the rounds so far is below ``min_time`` seconds
    (at most ``max_rounds``, default 4 x ``repeat``). On a loaded 2-core machine a short
    multi-threaded op sometimes waits tens of ms for its second thread; the best of many rounds
    is the undisturbed time. In smoke mode (``benchmarks.common.smoke``): one round after the warm-up.
    """
    if smoke():
        repeat, min_time, max_rounds = 1, 0.0, 1
    for fn in fns.values():
        fn()
    best = {name: float("inf") for name in fns}
    spent, rounds = 0.0, 0
    cap = 4 * repeat if max_rounds is None else max_rounds
    while rounds < repeat or (spent < min_time and rounds < cap):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            dt = time.perf_counter() - t0
            best[name] = min(best[name], dt)
            spent += dt
        rounds += 1
    return best


BENCH_THREADS = 1
"""torch intra-op threads inside the speed benchmarks (bench_uv, _mlp, _unet, _normal_maps,
_lightfield_vs_nerf). On this shared 2-core machine, with other jobs running, every parallel region
of a 2-thread op can wait tens of ms for its second thread (the paper U-Net at 256^2: 62 ms of
convolutions with 1 thread, 514 ms with 2); such waits hit an op made of many short calls far more
than the one long call it is compared with. Both sides of every ratio run with the same setting."""


@contextlib.contextmanager
def torch_threads(num: int = BENCH_THREADS) -> Iterator[None]:
    """Run the block with ``torch.set_num_threads(num)``, then restore the previous count."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(num)
    try:
        yield
    finally:
        torch.set_num_threads(before)
