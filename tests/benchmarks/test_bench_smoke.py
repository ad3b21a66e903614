"""Every benchmark module of ``benchmarks.run.MODULES`` in smoke mode (``python -m benchmarks.run --smoke``): one
subprocess runs them all at tiny sizes, one test per module reads its record from the report."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT_S = 300
"""Limit of the smoke run (it takes about 45 s on 2 cores)."""


def _modules() -> list[str]:
    """``benchmarks.run.MODULES``, read from its source (collection imports no benchmark)."""
    tree = ast.parse((ROOT / "benchmarks" / "run.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "MODULES" for t in node.targets):
            return list(ast.literal_eval(node.value))
    raise AssertionError("benchmarks/run.py defines no MODULES list")


MODULES = _modules()


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> dict:
    """The smoke run's exit status, output, report (``bench.json``) and wall seconds; its temporary files (the
    captures the modules synthesize) in the test's temporary folder."""
    out = tmp_path_factory.mktemp("bench_smoke")
    (out / "tmp").mkdir()
    env = {**os.environ, "TMPDIR": str(out / "tmp")}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "benchmarks.run", "--smoke", "--out", str(out)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    seconds = time.perf_counter() - t0
    report = out / "bench.json"
    if not report.is_file():
        pytest.fail(f"benchmarks.run --smoke wrote no report (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n"
                    f"{proc.stderr[-3000:]}")
    return {"returncode": proc.returncode, "stdout": proc.stdout, "report": json.loads(report.read_text()),
            "seconds": seconds}


@pytest.mark.parametrize("module", MODULES)
def test_module_runs_in_smoke_mode(smoke_run, module):
    record = smoke_run["report"]["modules"].get(module)
    assert record is not None, f"{module} was not run"
    assert record["error"] is None, f"{module} raised:\n{record['error']}"
    assert record["rows"] > 0, f"{module} returned no row"
    if len(record["skipped"]) == record["rows"]:
        pytest.skip(f"{module}: {'; '.join(record['skipped'])}")


def test_smoke_run_covers_every_module_and_judges_no_target(smoke_run):
    report = smoke_run["report"]
    assert report["smoke"] is True
    assert list(report["modules"]) == MODULES
    assert smoke_run["returncode"] == (1 if report["broken_modules"] else 0), smoke_run["stdout"][-3000:]
    assert all(r["passed"] is None for r in report["results"])
    assert "PASS" not in smoke_run["stdout"] and "FAIL" not in smoke_run["stdout"]
