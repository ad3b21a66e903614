"""The package as a user installs it: ``python -m build`` (the sdist, then the wheel built from the sdist), the
wheel in a fresh venv outside the repository.

The wheel goes into a new venv with ``--no-deps``; the dependencies come from this test run's
environment through a path entry (its ``.pth`` files, e.g. an editable deliffas, are not processed),
so the venv's deliffas is the wheel's. Then ``deliffas --version``, ``deliffas demo --quick`` and the three
examples run from another folder. ``--no-isolation``: the build uses this environment's setuptools instead
of installing one from the package index into a build environment.
"""

from __future__ import annotations

import os
import site
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest
from example_data import easymocap_rig, small_shards

import deliffas

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory):
    root = tmp_path_factory.mktemp("wheel")
    pytest.importorskip("build", reason="the build package (dev extra) makes the sdist and the wheel")
    build = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(root / "dist"), str(REPO)],
                           capture_output=True, text=True, timeout=600)
    if build.returncode != 0:
        pytest.fail(f"python -m build failed: {(build.stdout + build.stderr)[-2000:]}")
    sdists, wheels = list((root / "dist").glob("deliffas-*.tar.gz")), list((root / "dist").glob("deliffas-*.whl"))
    assert len(sdists) == 1 and len(wheels) == 1, sorted(p.name for p in (root / "dist").iterdir())
    wheel = wheels[0]
    env_dir = root / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    purelib = Path(subprocess.check_output([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                           text=True).strip())
    deps = [sysconfig.get_paths()["purelib"], *site.getsitepackages()]
    (purelib / "zz_test_dependencies.pth").write_text("\n".join(dict.fromkeys(deps)) + "\n")
    # without PYTHONPATH: a checkout on it (PYTHONPATH=<repo> runs) shows pip the deliffas.egg-info that
    # `pip wheel` just wrote there, and pip then skips the wheel as "already installed"
    clean = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "-q", str(wheel)],
                             capture_output=True, text=True, timeout=300, env=clean)
    if install.returncode != 0:
        pytest.fail(f"installing the wheel failed: {install.stderr[-2000:]}")
    return env_dir, wheel


def _run(env_dir: Path, args: list[str], cwd: Path, timeout: int = 600) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def _example_args(tmp_path: Path) -> list[list[str]]:
    """Command lines of the three examples on small data made here (cameras in EasyMocap's files, shards)."""
    ex = REPO / "examples"
    return [[str(ex / "01_geometry.py"), str(tmp_path / "ex1"), "--frames", "2", "--atlas", "16"],
            [str(ex / "02_uv_maps.py"), str(tmp_path / "ex2"), "--cameras", str(easymocap_rig(tmp_path / "emc"))],
            [str(ex / "03_custom_training.py"), str(small_shards(tmp_path)), "--steps", "3"]]


@pytest.mark.slow
def test_wheel_installs_and_runs_from_another_folder(wheel_venv, tmp_path):
    env_dir, wheel = wheel_venv
    py = str(env_dir / "bin" / "python")
    where = _run(env_dir, [py, "-c", "import deliffas, sys; print(deliffas.__file__)"], tmp_path)
    assert where.returncode == 0, where.stderr
    assert str(env_dir) in where.stdout and str(REPO) not in where.stdout  # the wheel's copy, not the repository
    version = _run(env_dir, [str(env_dir / "bin" / "deliffas"), "--version"], tmp_path)  # the console script
    assert version.stdout.strip() == f"deliffas {deliffas.__version__}" and wheel.name.startswith(
        f"deliffas-{deliffas.__version__}-")
    shipped = set(zipfile.ZipFile(wheel).namelist())  # the C kernels travel as package data
    sources = {f"deliffas/csrc/{p.name}" for p in (REPO / "deliffas" / "csrc").iterdir() if p.suffix in (".c", ".h")}
    assert sources and sources <= shipped, sorted(sources - shipped)
    player = {f"deliffas/engine/web/player/{p.name}" for p in (REPO / "deliffas" / "engine" / "web" / "player").iterdir()
              if p.suffix in (".js", ".html")}  # the web player of export --web, package data as well
    assert player and player <= shipped, sorted(player - shipped)
    for argv in _example_args(tmp_path):
        example = _run(env_dir, [py, *argv], tmp_path)
        assert example.returncode == 0, f"{argv[0]}: {example.stderr[-2000:]}"
    demo = _run(env_dir, [str(env_dir / "bin" / "deliffas"), "demo", "--quick", "--out", str(tmp_path / "demo")], tmp_path)
    assert demo.returncode == 0, demo.stderr[-2000:]
    assert (tmp_path / "demo" / "report.md").is_file()
