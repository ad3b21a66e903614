"""Runs every benchmark module, prints one table and writes ``bench_out/bench.json``.

Usage: ``python -m benchmarks.run [--only GROUP ...] [--out DIR] [--smoke]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

import torch

from benchmarks.common import SMOKE_ENV

MODULES = [
    "benchmarks.bench_posing",
    "benchmarks.bench_ingest",
    "benchmarks.bench_data",
    "benchmarks.bench_scale",
    "benchmarks.bench_engine",
    "benchmarks.bench_train",
    "benchmarks.bench_view",
    "benchmarks.bench_realtime",
    "benchmarks.bench_uv",
    "benchmarks.bench_mlp",
    "benchmarks.bench_unet",
    "benchmarks.bench_normal_maps",
    "benchmarks.bench_lightfield_vs_nerf",
]


def _machine() -> dict:
    return {"python": platform.python_version(), "torch": torch.__version__, "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "machine": platform.machine(),
            "processor": platform.processor() or platform.machine()}


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None, help="module name suffixes to run, e.g. posing")
    parser.add_argument("--out", type=Path, default=None, help="folder of bench.json (default bench_out, with "
                                                               "--smoke bench_out/smoke)")
    parser.add_argument("--smoke", action="store_true",
                        help=f"every module at tiny sizes with one timed repetition, no target judged (sets "
                             f"{SMOKE_ENV}=1); the exit status is 1 when a module raised")
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = Path("bench_out") / "smoke" if args.smoke else Path("bench_out")
    return args


def _run_modules(only: list[str] | None) -> tuple[list, dict[str, dict]]:
    """The rows of the selected modules and, per module, its row count, the names of its "skipped" rows, seconds and
    traceback (None if none)."""
    rows, modules = [], {}
    for name in MODULES:
        if only and not any(name.endswith(o) for o in only):
            continue
        t0, error, got = time.time(), None, []
        try:
            got = importlib.import_module(name).run()
        except Exception:  # a broken benchmark must not hide the others
            error = traceback.format_exc()
            print(error, file=sys.stderr)
        rows.extend(got)
        modules[name] = {"rows": len(got), "skipped": [r.name for r in got if r.name.startswith("skipped")],
                         "seconds": time.time() - t0, "error": error}
    return rows, modules


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    if args.smoke:  # read by benchmarks.common.smoke, here and in the probes the modules start
        os.environ[SMOKE_ENV] = "1"
    from deliffas.engine.memory import retain_freed_memory

    # as the CLI's train/eval/render do: both sides of every ratio run with freed memory kept in
    # the process, not faulted in again page by page on every call
    retained = retain_freed_memory()
    t0 = time.time()
    rows, modules = _run_modules(args.only)
    if args.smoke:  # tiny sizes: no figure is judged
        rows = [dataclasses.replace(r, passed=None) for r in rows]
    failures = [name for name, m in modules.items() if m["error"] is not None]
    header = f"{'group':<10} {'measurement':<58} {'value':>12} {'unit':<10} {'ratio':>8} {'target':<10} result"
    print(header)
    print("-" * len(header))
    for r in rows:
        ratio = f"{r.ratio:.2f}x" if r.ratio is not None else ""
        verdict = "" if r.passed is None else ("PASS" if r.passed else "FAIL")
        print(f"{r.group:<10} {r.name[:58]:<58} {r.value:>12.4g} {r.unit:<10} {ratio:>8} {r.target:<10} {verdict}")
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"machine": _machine(), "smoke": args.smoke, "freed_memory_retained": retained,
              "seconds": time.time() - t0, "results": [r.to_dict() for r in rows], "broken_modules": failures,
              "modules": modules}
    (args.out / "bench.json").write_text(json.dumps(report, indent=2))
    print(f"\n{len(rows)} measurements in {report['seconds']:.0f} s; freed memory kept in the process "
          f"(retain_freed_memory): {'yes' if retained else 'no, not glibc'}; JSON in {args.out / 'bench.json'}"
          + ("; smoke mode: tiny sizes, no target judged" if args.smoke else ""))
    if failures:
        print(f"broken modules: {', '.join(failures)}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
