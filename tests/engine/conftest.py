"""A tiny synthetic capture converted to shards, shared by the engine tests (built once per session)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_shards(tmp_path_factory):
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture

    root = tmp_path_factory.mktemp("engine_capture")
    synthesize_capture(root / "subject", SynthConfig(num_frames=6, num_test_frames=2, num_cameras=4, width=48,
                                                     height=48, test_cameras=(3,), seed=0))
    convert(root / "subject", root / "shards", ConvertConfig(atlas_res=32, progress=False))
    return root / "shards"
