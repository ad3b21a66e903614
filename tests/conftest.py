"""Shared test fixtures: the real DynaCap sample (skipped with a reason when absent), devices, the procedural
character and a tiny converted capture."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest

SAMPLE_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "dynacap-sample"


def pytest_addoption(parser):
    parser.addoption("--device", default="cpu", help="torch device for device-parametrised tests (default cpu)")


@pytest.fixture(autouse=True)
def _single_thread():
    """Run each test on one intra-op torch thread (restored afterwards).

    The tensors in tests are tiny; on a shared 2-core machine OpenMP threads only contend (a U-Net
    training step measured 0.07 s on one thread against 2.3 s on two while other processes ran).
    """
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def device(request):
    return request.config.getoption("--device")


@pytest.fixture
def unchecked():
    """A context manager that turns the test run's jaxtyping checks off inside it.

    The test run checks every deliffas annotation (``--jaxtyping-packages`` in pyproject.toml), so a
    mis-typed or mis-shaped argument raises jaxtyping's TypeCheckError before the function runs.
    Tests of a function's own run-time errors (what a user without the checker gets, e.g.
    ``check_shape``'s ValueError) call it inside ``with unchecked():``.
    """
    import jaxtyping

    @contextlib.contextmanager
    def off():
        before = jaxtyping.config.jaxtyping_disable
        jaxtyping.config.update("jaxtyping_disable", True)
        try:
            yield
        finally:
            jaxtyping.config.update("jaxtyping_disable", before)

    return off


@pytest.fixture(scope="session")
def sample_dir() -> Path:
    """The real DDC sample character (../shared/dynacap-sample next to the repo)."""
    if not (SAMPLE_DIR / "ddc.character").is_file():
        pytest.skip(f"DynaCap sample data not found at {SAMPLE_DIR} (../shared is absent)")
    return SAMPLE_DIR


@pytest.fixture(scope="session")
def sample_character(sample_dir):
    from deliffas.io.formats.dynacap.character import read_character

    return read_character(sample_dir / "ddc.character")


@pytest.fixture(scope="session")
def sample_motion(sample_dir, sample_character):
    from deliffas.io.formats.dynacap.character import read_motion

    return read_motion(sample_dir / "skeletoolToGTPose" / "poseAngles.motion", sample_character.skeleton.num_dofs)

PROCEDURAL_BUILD = dict(seed=0, target_faces=6000, texture_size=256)
"""The build every geometry test shares (small texture and face budget keep it fast)."""


@pytest.fixture(scope="session")
def procedural_build() -> dict:
    return dict(PROCEDURAL_BUILD)


@pytest.fixture(scope="session")
def procedural_character_path(tmp_path_factory) -> Path:
    """One build of PROCEDURAL_BUILD per test session (the .character is written last, so it marks completion)."""
    from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character

    d = tmp_path_factory.getbasetemp() / "procedural_s0_f6000_t256"
    path = d / "procedural.character"
    if not path.is_file():
        make_procedural_character(ProceduralConfig(d, **PROCEDURAL_BUILD))
    return path


@pytest.fixture(scope="session")
def tiny_shards(tmp_path_factory):
    """A tiny synthetic capture converted to shards (engine and benchmark tests; built once per session)."""
    from example_data import tiny_capture

    return tiny_capture(tmp_path_factory.mktemp("engine_capture"))[1]
