"""The package as a user installs it: a wheel built from the repository, in a fresh venv outside it.

The wheel goes into a new venv with ``--no-deps``; the dependencies come from this test run's
environment through a path entry (its ``.pth`` files, e.g. an editable deliffas, are not processed),
so the venv's deliffas is the wheel's. Then ``deliffas --version``, ``deliffas demo --quick`` and an
example run from another folder.
"""

from __future__ import annotations

import os
import site
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

import deliffas

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory):
    root = tmp_path_factory.mktemp("wheel")
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(root / "dist"), str(REPO)],
                           capture_output=True, text=True, timeout=600)
    if build.returncode != 0:
        pytest.fail(f"pip wheel failed: {build.stderr[-2000:]}")
    wheel = next((root / "dist").glob("deliffas-*.whl"))
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


def test_wheel_installs_and_runs_from_another_folder(wheel_venv, tmp_path):
    env_dir, wheel = wheel_venv
    py = str(env_dir / "bin" / "python")
    where = _run(env_dir, [py, "-c", "import deliffas, sys; print(deliffas.__file__)"], tmp_path)
    assert where.returncode == 0, where.stderr
    assert str(env_dir) in where.stdout and str(REPO) not in where.stdout  # the wheel's copy, not the repository
    version = _run(env_dir, [str(env_dir / "bin" / "deliffas"), "--version"], tmp_path)  # the console script
    assert version.stdout.strip() == f"deliffas {deliffas.__version__}" and wheel.name.startswith(
        f"deliffas-{deliffas.__version__}-")
    example = _run(env_dir, [py, str(REPO / "examples" / "01_geometry.py"), str(tmp_path / "ex"), "--frames", "2",
                             "--atlas", "16"], tmp_path)
    assert example.returncode == 0, example.stderr[-2000:]
    demo = _run(env_dir, [str(env_dir / "bin" / "deliffas"), "demo", "--quick", "--out", str(tmp_path / "demo")], tmp_path)
    assert demo.returncode == 0, demo.stderr[-2000:]
    assert (tmp_path / "demo" / "report.md").is_file()
