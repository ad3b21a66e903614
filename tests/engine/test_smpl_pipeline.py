"""SMPL end to end through the CLI: synth --body-model -> convert -> train -> eval --json -> render --motion.

The body is the license-free procedural body in SMPL layout; a user's SMPL file takes the same path.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from deliffas.cli import main
from deliffas.data.shards import ShardSet
from deliffas.geometry.smpl_motion import procedural_smpl_motion
from deliffas.io.body_models.amass import write_smpl_motion


@pytest.fixture(scope="module")
def smpl_subject(tmp_path_factory):
    root = tmp_path_factory.mktemp("smpl_capture")
    assert main(["synth", str(root / "subject"), "--body-model", "procedural", "--frames", "6", "--test-frames",
                 "2", "--cameras", "4", "--size", "48x48", "--test-cameras", "3,"]) == 0
    return root


def test_synth_writes_an_smpl_subject(smpl_subject):
    subject = smpl_subject / "subject"
    assert (subject / "body" / "smpl_procedural.npz").is_file() and (subject / "body" / "smpl_procedural_uv.obj").is_file()
    assert (subject / "training" / "poses.npz").is_file() and not (subject / "character").exists()
    assert json.loads((subject / "synth.json").read_text())["body"]["kind"] == "smpl"


def test_convert_train_eval_render(smpl_subject, tmp_path, capsys):
    subject, shards, run = smpl_subject / "subject", tmp_path / "shards", tmp_path / "run"
    assert main(["convert", str(subject), str(shards), "--atlas-res", "32", "--no-progress"]) == 0
    spec = ShardSet(shards).meta.template_spec()
    assert spec.kind == "smpl" and spec.option("num_betas") == 10 and "uv_obj" in spec.files
    assert main(["train", str(shards), "--out", str(run), "--model", "two_surface", "--preset", "tiny",
                 "--iters", "30", "--workers", "0", "--cameras-per-frame", "2", "--checkpoint-every", "30",
                 "--preview-every", "30"]) == 0
    capsys.readouterr()
    assert main(["eval", str(run), "--split", "novel_view", "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert np.isfinite(result["psnr"]) and 0 < result["ssim"] <= 1
    motion = tmp_path / "walk.npz"
    write_smpl_motion(motion, procedural_smpl_motion(3, seed=5))
    assert main(["render", str(run), "--out", str(tmp_path / "frames"), "--motion", str(motion), "--orbit"]) == 0
    assert len(list((tmp_path / "frames").glob("*.png"))) == 3
    # a DDC motion for an SMPL template is refused before rendering, naming both
    bad = tmp_path / "poses.motion"
    bad.write_text("Skeletool Motion File V1.0\n0 0 0 0\n")
    assert main(["render", str(run), "--out", str(tmp_path / "x"), "--motion", str(bad)]) == 2
    assert "smpl template takes a .npz motion" in capsys.readouterr().err


def test_pose_cli_on_smpl(smpl_subject, tmp_path, capsys):
    model = smpl_subject / "subject" / "body" / "smpl_procedural.npz"
    motion = smpl_subject / "subject" / "training" / "poses.npz"
    assert main(["pose", str(model), str(motion), "--frame", "2", "--out", str(tmp_path / "p.obj")]) == 0
    assert "(frame 2, smpl)" in capsys.readouterr().out
    text = (tmp_path / "p.obj").read_text()
    assert text.count("\nv ") > 1000 and "\nvt " in text
    assert main(["pose", str(model), str(motion), "--frame", "99", "--out", str(tmp_path / "q.ply")]) == 2
    assert "frame 99" in capsys.readouterr().err and not (tmp_path / "q.ply").exists()
