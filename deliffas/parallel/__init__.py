"""Running independent tasks in parallel: in-process, a local process pool, or a Dask cluster.

A shared leaf: importable from any layer, importing no deliffas layer. :func:`open_executor` is the
one seam a pipeline needs: it hands tasks and a per-worker setup to the executor the user chose
and yields the results as they complete. dask is imported only when a Dask executor is opened.
"""

from deliffas.parallel.dask_target import DaskTarget, parse_dask_target
from deliffas.parallel.executors import InProcessExecutor, PoolExecutor, TaskExecutor, open_executor
from deliffas.parallel.pool import process_map

__all__ = ["TaskExecutor", "InProcessExecutor", "PoolExecutor", "open_executor", "process_map", "DaskTarget",
           "parse_dask_target"]
