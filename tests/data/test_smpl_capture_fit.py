"""SMPL fitted to a DDC capture frame by frame, then the same images converted with the SMPL template."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deliffas.cli import main
from deliffas.data.shards import ShardSet
from deliffas.geometry.smpl_body import make_procedural_smpl
from deliffas.io.body_models.amass import read_smpl_motion


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    return make_procedural_smpl(tmp_path_factory.mktemp("fit_body"), target_verts=1200)


def test_fit_smpl_then_convert_with_smpl(subject, body, tmp_path, capsys, tiny):
    fit = tmp_path / "fit"
    # few iterations: this checks the path, not the accuracy (docs/geometry.md states measured residuals)
    assert main(["fit-smpl", str(subject), "--model", str(body), "--out", str(fit), "--first-iters", "40",
                 "--frame-iters", "5"]) == 0
    report = json.loads((fit / "fit.json").read_text())
    assert set(report["sequences"]) == {"training", "testing"}
    assert all(np.isfinite(s["residual_mm_mean"]) and s["residual_mm_mean"] < 80 for s in report["sequences"].values())
    motion = read_smpl_motion(fit / "training.npz")
    assert motion.frames.tolist() == list(range(tiny["num_frames"]))
    shards = tmp_path / "shards"
    # --no-check: a 40-step fit is crude on purpose (the silhouette check rightly flags it)
    assert main(["convert", str(subject), str(shards), "--atlas-res", "32", "--no-progress", "--no-check", "--template", str(body),
                 "--motions", f"training={fit / 'training.npz'}", "--motions", f"testing={fit / 'testing.npz'}"]) == 0
    meta = ShardSet(shards).meta
    assert meta.template_spec().kind == "smpl"
    assert main(["fit-smpl", str(subject), "--model", str(body), "--out", str(fit)]) == 2  # never replaced unasked
    assert "--overwrite" in capsys.readouterr().err
