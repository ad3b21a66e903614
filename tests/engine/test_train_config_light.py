"""Building a ``TrainConfig`` checks its values and does no work: no C compiler runs, no uv source is resolved."""

from __future__ import annotations

from deliffas import native
from deliffas.engine.train_config import TrainConfig


def test_building_a_config_compiles_nothing(monkeypatch):
    def no_build(*args, **kwargs):
        raise AssertionError("a config built a C library")

    monkeypatch.setattr(native, "build_library", no_build)
    cfg = TrainConfig(shards="s", out="o", uv="auto")
    assert cfg.uv == "auto"
