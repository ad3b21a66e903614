"""One conversion in a fresh process, run by bench_scale: its timings and the workers' peak resident sets.

``python -m benchmarks._convert_probe SUBJECT OUT JSON_CONFIG`` prints JSON: the ``ConvertResult``
fields, ``cpu_seconds`` (this process's CPU time in ``convert``: the core-seconds the conversion
cost with ``--jobs 1``, whatever else runs on the machine) and ``worker_peak_rss`` (bytes, one per worker process: the peak resident set, ``VmHWM``,
of each process that built shards). ``JSON_CONFIG`` holds ``ConvertConfig`` fields; with
``"dask_workers": N`` a LocalCluster of N worker processes converts (its workers' peaks are read
before it closes), else this process does (``--jobs 1``) and its own peak is the worker's.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path


def _peak_rss() -> int:
    """This process's peak resident set (``VmHWM``), bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc/self/status (Linux only)")


def main(subject: str, out: str, config: dict) -> dict:
    from deliffas.data.convert import ConvertConfig, convert

    workers = int(config.pop("dask_workers", 0))
    cfg = ConvertConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in config.items()}, progress=False)
    cpu = time.process_time()
    if not workers:
        res = convert(subject, out, cfg)
        peaks = [_peak_rss()]
    else:
        import distributed

        with distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                                      dashboard_address=None) as lc, distributed.Client(lc) as client:
            res = convert(subject, out, dataclasses.replace(cfg, dask=lc.scheduler_address))
            peaks = sorted(client.run(_peak_rss).values())
    record = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(res).items()}
    return {**record, "cpu_seconds": time.process_time() - cpu, "worker_peak_rss": peaks}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2], json.loads(sys.argv[3]))))
