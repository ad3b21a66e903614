"""scripts/device_check.sh runs on the CPU as it would on a bare GPU box: the CPU-only geometry packages are
made unimportable, the capture comes from --prepare, and every check passes (make test-slow)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCKED = ("open3d", "pymeshlab", "xatlas", "pycolmap", "trimesh", "viser", "av", "flip_evaluator")


@pytest.mark.slow
def test_device_check_on_cpu_without_the_geometry_packages(tmp_path):
    from benchmarks.device_check import prepare

    data = tmp_path / "data"
    prepare(data, frames=3, cameras=4, size=48, atlas_res=32)
    assert (data / "vendor" / "jaxtyping" / "__init__.py").is_file()
    stubs = tmp_path / "stubs"  # each blocked package raises ImportError on import, as if not installed
    for name in BLOCKED:
        (stubs / name).mkdir(parents=True)
        (stubs / name / "__init__.py").write_text(f"raise ImportError('{name} is not installed (device check)')\n")
    env = {**os.environ, "PYTHONPATH": str(stubs), "PYTHON": sys.executable}
    out = tmp_path / "record.json"
    r = subprocess.run([str(ROOT / "scripts" / "device_check.sh"), "--data", str(data), "--device", "cpu", "--json",
                        str(out)], capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    record = json.loads(out.read_text())
    assert record["passed"] and record["device"] == "cpu"
    assert record["eval"]["uv"] == "torch" and set(record["eval"]["stage_ms"]) == {"uv", "cnn", "sample", "mlp"}
    assert record["eval_default_uv"]["uv"] == "raster" and record["eval_default_uv"]["fps"] > 0
    assert record["trainer"]["it_per_s"] > 0 and record["trainer"]["uv"] == "torch"
    assert record["trainer_default_uv"]["it_per_s"] > 0 and record["trainer_default_uv"]["uv"] == "raster"
    assert [c["preset"] for c in record["cases"]] == ["tiny", "small"]
    for case in record["cases"]:
        assert case["train"]["it_per_s"] > 0 and case["render"]["fps"] > 0
        assert set(case["render"]["stage_ms"]) == {"uv", "cnn", "sample", "mlp"}
        assert case["render"]["uv"] == "torch" and case["render_default_uv"]["uv"] == "raster"
        assert case["render_default_uv"]["fps"] > 0
        assert case["agreement"]["psnr_db"] >= 50 and case["rays_per_image"] > 0
    assert "[device_check] python" in r.stdout and "passed" in r.stdout


def test_device_check_without_shards_says_how_to_make_them(tmp_path):
    r = subprocess.run([str(ROOT / "scripts" / "device_check.sh"), "--data", str(tmp_path / "none"), "--device",
                        "cpu"], capture_output=True, text=True, env={**os.environ, "PYTHON": sys.executable})
    assert r.returncode == 2 and "--prepare" in r.stderr and len(r.stderr.strip().splitlines()) == 1
