"""Training does not import evaluation: loading runs and shading cameras live in their own modules."""

from __future__ import annotations

import pytest

TRAINING = "deliffas.engine.train"
EVALUATION = ("deliffas.engine.evaluate", "deliffas.engine.shading", "deliffas.fast",
              "deliffas.models.metrics")
UV_SOURCES = ("deliffas.fast", "deliffas.fast.config", "deliffas.fast.rasterize", "deliffas.fast.uv_sources")
"""The uv sources (``fast.uv_sources``, with the C rasteriser) serve training too (``TrainConfig.uv``, declared in
``fast.config``): training imports them, and nothing else of the fast path."""


def test_training_import_graph_excludes_evaluation():
    grimp = pytest.importorskip("grimp", reason="grimp (import-linter's graph library, dev extra) builds the graph")
    graph = grimp.build_graph("deliffas")  # every import statement, function-local ones included
    imported = graph.find_upstream_modules(TRAINING)
    leaked = sorted(m for m in imported if any(m == e or m.startswith(e + ".") for e in EVALUATION)
                    and m not in UV_SOURCES)
    assert not leaked, f"{TRAINING} imports {leaked}"
    assert "deliffas.engine.runs" in imported  # the run loader the avatar writer uses, without the evaluator


def test_one_shard_set_per_command(tiny_shards, tmp_path, monkeypatch):
    """train and eval open the shard folder once and pass the ShardSet down (avatar, identity, dataset...)."""
    from deliffas.data.shards import ShardSet
    from deliffas.engine.evaluate import EvalConfig, evaluate
    from deliffas.engine.train import TrainConfig, train

    opened: list[str] = []
    original = ShardSet.__init__

    def counting(self, out_dir):
        opened.append(str(out_dir))
        original(self, out_dir)

    monkeypatch.setattr(ShardSet, "__init__", counting)
    run = tmp_path / "run"
    train(TrainConfig(shards=str(tiny_shards), out=str(run), model="two_surface", preset="tiny", iters=1,
                      cameras_per_frame=1, protocol="all", num_workers=0, checkpoint_every=1, preview_every=0,
                      log_every=1, progress=False))
    assert len(opened) == 1, opened
    opened.clear()
    evaluate(EvalConfig(run=str(run), split="novel_view", max_frames=1))
    assert len(opened) == 1, opened
