"""A process pool for independent tasks (conversion shards, synthetic frame chunks): spawned workers
that die with their parent, and a dead worker reported instead of a hang.

A shared leaf: importable from any layer, importing no deliffas layer.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from typing import Sequence

__all__ = ["process_map"]


def process_map(fn, tasks: Sequence[tuple], jobs: int, initializer=None, initargs: tuple = (), poll_s: float = 2.0):
    """Run ``fn(*task)`` for every task in ``jobs`` spawned processes; yield results as they complete.

    Spawn (not fork) keeps torch/open3d/h5py state out of the workers. A worker that dies (e.g. a
    signal) raises RuntimeError naming its pid and exit code instead of hanging; on any error the
    remaining workers (started here) are terminated by handle. Keep ``tasks`` small and put large
    arrays into ``initargs``: CPython's executor can deadlock when a worker dies while a task larger
    than the pipe buffer (64 kB) is being written to it. Workers die with the calling process, even
    when it is killed with SIGKILL (``_exit_when_parent_dies``), so no orphan keeps writing. Callers
    need the ``if __name__ == "__main__"`` guard in their main script (spawn re-imports it).
    """
    pool = ProcessPoolExecutor(jobs, mp_context=get_context("spawn"), initializer=_worker_init,
                               initargs=(os.getpid(), initializer, initargs))
    try:
        pending = {pool.submit(fn, *t) for t in tasks}
        while pending:
            done, pending = wait(pending, timeout=poll_s, return_when=FIRST_COMPLETED)
            for fut in done:
                yield fut.result()
            dead = [p for p in list(getattr(pool, "_processes", {}).values()) if p.exitcode not in (None, 0)]
            if dead and pending:
                raise RuntimeError(f"worker process {dead[0].pid} died (exit code {dead[0].exitcode}); "
                                   f"{len(pending)} tasks unfinished")
    except BaseException:
        for proc in list(getattr(pool, "_processes", {}).values()):
            if proc.is_alive():
                proc.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


_PR_SET_PDEATHSIG = 1


def _exit_when_parent_dies(parent_pid: int) -> None:
    """Make this worker die with the process that started it (even by SIGKILL).

    Without it, workers of a killed ``convert --jobs N`` live on as orphans and keep renaming shards
    into the output folder while a ``--resume`` or ``--overwrite`` runs there. Linux: the kernel
    sends SIGKILL on the parent's death (``PR_SET_PDEATHSIG``); elsewhere a daemon thread polls the
    parent id every 0.2 s.
    """
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
                if os.getppid() != parent_pid:  # died before prctl took effect
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.2)
        os._exit(1)

    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _worker_init(parent_pid: int, initializer, initargs: tuple) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the parent reports it, no traceback
    _exit_when_parent_dies(parent_pid)
    if initializer is not None:
        initializer(*initargs)
