"""The Dask executor of :func:`deliffas.parallel.open_executor`: one Dask task per task, on a running
scheduler or on a LocalCluster of N worker processes started here.

Per-worker setup: the ``(setup, setup_args)`` pair travels to each worker once, inside a worker
plugin registered under a name unique to this run; a worker builds its state on its first task and
keeps it in that plugin (so two runs sharing a cluster never share state). A worker runs one task
at a time (a process-wide lock), which bounds its memory and keeps torch single-threaded results
identical to the process pool's. A worker process that dies mid-task is restarted by its nanny and
the scheduler runs the task again (up to ``distributed.scheduler.allowed-failures`` times).
dask is imported here, at call time; without it the error names the package to install.
"""

from __future__ import annotations

import logging
import threading
import uuid
from typing import Any, Callable, no_type_check

from deliffas.parallel.dask_target import parse_dask_target
from deliffas.optional import import_optional

__all__ = ["DaskExecutor"]

log = logging.getLogger(__name__)

_TASK_LOCK = threading.Lock()
"""One task at a time per worker process, whatever the worker's thread count."""


def _import_distributed():
    return import_optional("distributed", '--dask needs the dask distributed scheduler: pip install "dask[distributed]"')


def _make_plugin(name: str, setup: Callable, setup_args: tuple):
    from distributed.diagnostics.plugin import WorkerPlugin

    # no_type_check: Dask pickles this local class by value, and the test run's type-check wrappers
    # (jaxtyping's import hook) hold weakrefs, which do not pickle.
    @no_type_check
    class _SetupPlugin(WorkerPlugin):
        """Carries one run's per-worker setup; the state is built lazily by the first task."""

        def __init__(self):
            self.name, self.setup_fn, self.setup_args, self.state = name, setup, setup_args, None

        def teardown(self, worker) -> None:
            self.state = None

    return _SetupPlugin()


def _run_task(plugin_name: str, fn: Callable, *task) -> Any:
    """Worker side: this run's state (built on the worker's first task), then ``fn(state, *task)``."""
    from distributed import get_worker

    plugin = get_worker().plugins[plugin_name]
    with _TASK_LOCK:
        if plugin.state is None:
            plugin.state = plugin.setup_fn(*plugin.setup_args)
        return fn(plugin.state, *task)


class DaskExecutor:
    """Tasks on a Dask cluster: ``target`` is a scheduler address or ``local:N``."""

    def __init__(self, target: str, connect_timeout_s: float = 5.0):
        spec = parse_dask_target(target)
        distributed = _import_distributed()
        self.cluster = None
        if spec.address is None:
            # bound to 127.0.0.1; one thread per worker; a nanny per worker restarts it when it dies
            self.cluster = distributed.LocalCluster(n_workers=spec.local_workers, threads_per_worker=1,
                                                    processes=True, host="127.0.0.1",
                                                    dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
            address = self.cluster.scheduler_address
        else:
            address = spec.address
        try:
            self.client = distributed.Client(address, timeout=f"{connect_timeout_s}s", set_as_default=False)
        except (OSError, TimeoutError) as err:
            self._close_cluster()
            raise ConnectionError(f"--dask {target}: no Dask scheduler answered at {address} within "
                                  f"{connect_timeout_s:g} s ({type(err).__name__})") from None
        info = self.client.scheduler_info()
        services = info.get("services", {})
        self.dashboard = self.client.dashboard_link if "dashboard" in services else "none (pip install bokeh)"
        log.info("Dask scheduler %s: %d workers; dashboard %s", address, len(info.get("workers", {})), self.dashboard)
        if not info.get("workers"):
            log.warning("Dask scheduler %s has no workers yet: the shards wait until workers join", address)

    def map(self, fn, tasks, setup, setup_args, local_state=None):
        """Submit every task; yield results as they complete (the in-process ``local_state`` is unused)."""
        from distributed import as_completed

        if not tasks:  # nothing to send the setup for (e.g. a --resume of a finished conversion)
            return
        run = f"deliffas-{uuid.uuid4().hex[:12]}"
        self.client.register_plugin(_make_plugin(run, setup, setup_args), name=run)
        futures = [self.client.submit(_run_task, run, fn, *t, key=f"{run}-{i}", pure=False)
                   for i, t in enumerate(tasks)]
        try:
            for future in as_completed(futures, loop=self.client.loop):
                yield future.result()
        finally:
            self.client.cancel(futures)
            try:
                self.client.unregister_worker_plugin(run)
            except Exception as err:  # noqa: BLE001 - a closing cluster may refuse; the run is over anyway
                log.debug("unregistering %s: %s", run, err)

    def _close_cluster(self) -> None:
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None

    def close(self) -> None:
        client, self.client = getattr(self, "client", None), None
        if client is not None:
            client.close()
        self._close_cluster()

    def __enter__(self) -> "DaskExecutor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
