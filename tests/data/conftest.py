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
    from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character

    return make_procedural_character(ProceduralConfig(tmp_path_factory.mktemp("character"), seed=0,
                                                      target_faces=3000, texture_size=256))


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


SMPL_TINY = dict(num_frames=4, num_test_frames=1, num_cameras=4, width=64, height=64, seed=1, body_model="procedural",
                 fps=3.0)
"""The SMPL-body session capture: fps 3 so that consecutive frames differ (frame-offset detection)."""


@pytest.fixture(scope="session")
def smpl_subject(tmp_path_factory) -> Path:
    """A synthetic capture of the procedural SMPL-layout body (4 training + 1 testing frames, 4 cameras, 64x64)."""
    from deliffas.data.synth import SynthConfig, synthesize_capture

    out = tmp_path_factory.mktemp("smpl_subject")
    synthesize_capture(out, SynthConfig(**SMPL_TINY))
    return out


@pytest.fixture(scope="session")
def smpl_model(smpl_subject) -> Path:
    """The SMPL model file of ``smpl_subject`` (what a user passes as --template)."""
    return smpl_subject / "body" / "smpl_procedural.npz"


@pytest.fixture(scope="session")
def exported(tmp_path_factory, smpl_subject):
    """``exported(fmt)``: the training sequence of ``smpl_subject`` written in capture format ``fmt`` (cached)."""
    from deliffas.data.export_capture import export_capture
    from deliffas.data.subjects import parse_subject

    cache: dict[str, Path] = {}
    subject = parse_subject(smpl_subject)

    def get(fmt: str) -> Path:
        if fmt not in cache:
            cache[fmt] = export_capture(subject, tmp_path_factory.mktemp(f"export_{fmt}") / f"cap_{fmt}", fmt,
                                        jpeg_quality=100)
        return cache[fmt]
    return get


@pytest.fixture
def triangle_scene() -> dict:
    """One flat triangle (uv-mapped to a uniform 0.8 grey texture) facing one 32 x 32 camera at z = +3000, its edges
    crossing pixels: ``render_views`` keyword arguments without the shading."""
    import numpy as np

    from deliffas.io.cameras import Camera

    faces = np.array([[0, 1, 2]])
    E = np.eye(4)
    E[:3, :3] = np.diag([1.0, -1.0, -1.0])  # camera at z = +3000 looking down -z, y down
    E[2, 3] = 3000.0
    return {"verts": np.array([[-400.0, -400, 0], [400, -400, 0], [-400, 400, 0]]), "faces": faces,
            "uvs": np.array([[0.0, 0], [1, 0], [0, 1]]), "face_uvs": faces,
            "texture": np.full((2, 2, 3), 0.8, np.float32),
            "cameras": [Camera("c", np.array([[60.0, 0, 16], [0, 60, 16], [0, 0, 1]]), E, 32, 32)]}
