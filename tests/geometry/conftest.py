"""Fixtures shared by the geometry tests: one procedural character build per session."""

from __future__ import annotations

from pathlib import Path

import pytest

PROCEDURAL_BUILD = dict(seed=0, target_faces=6000, texture_size=256)
"""The build every geometry test shares (small texture and face budget keep it fast)."""


@pytest.fixture(scope="session")
def procedural_build() -> dict:
    return dict(PROCEDURAL_BUILD)


@pytest.fixture(scope="session")
def procedural_character_path(tmp_path_factory) -> Path:
    """One build of PROCEDURAL_BUILD per test session (the .character is written last, so it marks completion)."""
    from deliffas.geometry.procedural import make_procedural_character

    d = tmp_path_factory.getbasetemp() / "procedural_s0_f6000_t256"
    path = d / "procedural.character"
    if not path.is_file():
        make_procedural_character(d, **PROCEDURAL_BUILD)
    return path
