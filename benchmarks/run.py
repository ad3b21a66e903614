"""Runs every benchmark module, prints one table and writes ``bench_out/bench.json``.

Usage: ``python -m benchmarks.run [--only GROUP ...] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import sys
import time
import traceback
from pathlib import Path

import torch

MODULES = [
    "benchmarks.bench_posing",
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
    import os

    return {"python": platform.python_version(), "torch": torch.__version__, "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "machine": platform.machine(),
            "processor": platform.processor() or platform.machine()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None, help="module name suffixes to run, e.g. posing")
    parser.add_argument("--out", type=Path, default=Path("bench_out"))
    args = parser.parse_args(argv)
    from deliffas.engine.memory import retain_freed_memory

    # as the CLI's train/eval/render do: both sides of every ratio run with freed memory kept in
    # the process, not faulted in again page by page on every call
    retained = retain_freed_memory()
    rows, failures = [], []
    t0 = time.time()
    for name in MODULES:
        if args.only and not any(name.endswith(o) for o in args.only):
            continue
        try:
            mod = importlib.import_module(name)
            rows.extend(mod.run())
        except Exception:  # a broken benchmark must not hide the others
            failures.append(name)
            traceback.print_exc()
    header = f"{'group':<10} {'measurement':<58} {'value':>12} {'unit':<10} {'ratio':>8} {'target':<10} result"
    print(header)
    print("-" * len(header))
    for r in rows:
        ratio = f"{r.ratio:.2f}x" if r.ratio is not None else ""
        verdict = "" if r.passed is None else ("PASS" if r.passed else "FAIL")
        print(f"{r.group:<10} {r.name[:58]:<58} {r.value:>12.4g} {r.unit:<10} {ratio:>8} {r.target:<10} {verdict}")
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"machine": _machine(), "freed_memory_retained": retained, "seconds": time.time() - t0,
              "results": [r.to_dict() for r in rows], "broken_modules": failures}
    (args.out / "bench.json").write_text(json.dumps(report, indent=2))
    print(f"\n{len(rows)} measurements in {report['seconds']:.0f} s; freed memory kept in the process "
          f"(retain_freed_memory): {'yes' if retained else 'no, not glibc'}; JSON in {args.out / 'bench.json'}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
