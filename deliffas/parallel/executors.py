"""The executor seam: tasks ``fn(state, *task)`` with a per-worker ``state = setup(*setup_args)``.

Every executor builds the state once per worker (not once per task), so large shared inputs (a
capture with its pose arrays) travel once per worker and tasks stay small. Results are yielded as
tasks complete, in any order. Executors are context managers; opening one connects to its workers,
so a pipeline opens it before writing anything (an unreachable scheduler then writes nothing).
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Iterator, Protocol, Sequence, runtime_checkable

from deliffas.parallel.pool import process_map

__all__ = ["TaskExecutor", "InProcessExecutor", "PoolExecutor", "open_executor"]

log = logging.getLogger(__name__)


@runtime_checkable  # isinstance-able, so annotations of it can be checked at run time
class TaskExecutor(Protocol):
    """Runs ``fn(state, *task)`` for every task, ``state`` built by ``setup(*setup_args)`` once per worker."""

    def map(self, fn: Callable, tasks: Sequence[tuple], setup: Callable, setup_args: tuple,
            local_state: Any = None) -> Iterator[Any]:
        """Yield the results as tasks complete. ``local_state``: the state already built in this
        process, used by executors that run tasks here."""
        ...

    def close(self) -> None:
        """Release workers (idempotent)."""
        ...

    def __enter__(self) -> "TaskExecutor": ...

    def __exit__(self, *exc) -> None: ...


class _Closing:
    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class InProcessExecutor(_Closing):
    """Tasks one after the other in this process."""

    def map(self, fn, tasks, setup, setup_args, local_state=None):
        state = setup(*setup_args) if local_state is None else local_state
        for task in tasks:
            yield fn(state, *task)


_pool_state: Any = None
"""This pool worker's state (set once by ``_pool_setup``; spawn gives each worker its own)."""


def _pool_setup(setup: Callable, setup_args: tuple) -> None:
    global _pool_state
    _pool_state = setup(*setup_args)


def _pool_call(fn: Callable, *task) -> Any:
    return fn(_pool_state, *task)


class PoolExecutor(_Closing):
    """``jobs`` spawned worker processes on this machine (:func:`process_map`); in-process for one task."""

    def __init__(self, jobs: int):
        self.jobs = int(jobs)

    def map(self, fn, tasks, setup, setup_args, local_state=None):
        if self.jobs <= 1 or len(tasks) <= 1:
            yield from InProcessExecutor().map(fn, tasks, setup, setup_args, local_state)
            return
        yield from process_map(_pool_call, [(fn, *t) for t in tasks], min(self.jobs, len(tasks)), _pool_setup,
                               (setup, setup_args))


def open_executor(jobs: int = 1, dask: str | None = None, *, connect_timeout_s: float = 5.0) -> TaskExecutor:
    """The executor of ``--jobs N`` (a local process pool) or ``--dask ADDRESS|local:N`` (a Dask cluster).

    With ``dask``, connects now (or starts the LocalCluster): ConnectionError when no scheduler
    answers within ``connect_timeout_s``, ImportError naming ``dask[distributed]`` when it is missing.
    """
    if dask is None:
        return PoolExecutor(jobs)
    from deliffas.parallel.dask_executor import DaskExecutor  # local: dask is imported only here, at call time

    return DaskExecutor(dask, connect_timeout_s=connect_timeout_s)
