"""Fixtures of the data tests: one tiny procedural character, a synthetic subject and its conversion.

Everything is built once per session at tiny sizes (64 x 64 images, 3 + 1 frames, 4 cameras) and
treated as read-only; tests that modify files copy them first.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

TINY = dict(num_frames=3, num_cameras=4, width=64, height=64, seed=1)


@pytest.fixture(scope="session")
def tiny() -> dict:
    """SynthConfig fields of the session subject."""
    return dict(TINY)


@pytest.fixture(scope="session")
def tiny_character(tmp_path_factory) -> Path:
    """The procedural character (label 12 = skirt) at a small face and texture budget."""
    from deliffas.geometry.procedural import make_procedural_character

    return make_procedural_character(tmp_path_factory.mktemp("character"), seed=0, target_faces=3000,
                                     texture_size=256)


@pytest.fixture(scope="session")
def subject(tmp_path_factory, tiny_character) -> Path:
    """A synthetic subject with images and FFV1 videos (3 training + 1 testing frames, 4 cameras, 64x64)."""
    from deliffas.data.synth import SynthConfig, synthesize_capture

    out = tmp_path_factory.mktemp("subject")
    synthesize_capture(out, SynthConfig(**TINY, character=str(tiny_character), videos=True))
    return out


@pytest.fixture(scope="session")
def converted(tmp_path_factory, subject) -> Path:
    """``subject`` converted with 2 frames per shard and a 32 x 32 atlas."""
    from deliffas.data.convert import ConvertConfig, convert

    out = tmp_path_factory.mktemp("converted") / "out"
    convert(subject, out, ConvertConfig(shard_frames=2, atlas_res=32, progress=False))
    return out


@pytest.fixture
def converted_copy(tmp_path, converted) -> Path:
    """A private copy of ``converted`` that a test may break."""
    dst = tmp_path / "out"
    shutil.copytree(converted, dst)
    return dst
