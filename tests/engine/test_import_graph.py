"""Training does not import evaluation: loading runs and shading cameras live in their own modules."""

from __future__ import annotations

import pytest

TRAINING = "deliffas.engine.train"
EVALUATION = ("deliffas.engine.evaluate", "deliffas.engine.shading", "deliffas.engine.realtime", "deliffas.fast",
              "deliffas.models.metrics")


def test_training_import_graph_excludes_evaluation():
    grimp = pytest.importorskip("grimp", reason="grimp (import-linter's graph library, dev extra) builds the graph")
    graph = grimp.build_graph("deliffas")  # every import statement, function-local ones included
    imported = graph.find_upstream_modules(TRAINING)
    leaked = sorted(m for m in imported if any(m == e or m.startswith(e + ".") for e in EVALUATION))
    assert not leaked, f"{TRAINING} imports {leaked}"
    assert "deliffas.engine.runs" in imported  # the run loader the avatar writer uses, without the evaluator
