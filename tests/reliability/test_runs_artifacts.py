"""Runs as artifacts: engine commands never replace a user's work, refuse mixed identities and bad values
with one error line, and a run exported as an ``.avatar`` renders after its shards and subject are gone.

Every refusal is checked to leave the user's files byte-identical (checksums before and after).
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
import torch

from deliffas.cli import main

TRAIN = ["--preset", "tiny", "--iters", "2", "--workers", "0", "--checkpoint-every", "2", "--preview-every", "0"]


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(capsys, argv, match):
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error:" in err[0] and match in err[0], err
    assert "Traceback" not in err[0]


@pytest.fixture(scope="module")
def rel_run(rel_reference, tmp_path_factory) -> Path:
    """A 2-iteration run on the session capture (read-only: tests copy it)."""
    run = tmp_path_factory.mktemp("artifacts") / "run"
    assert main(["train", str(rel_reference), "--out", str(run), *TRAIN]) == 0
    return run


@pytest.fixture(scope="module")
def portable(tmp_path_factory) -> dict[str, Path]:
    """Another character's capture whose template lives inside its subject, its shards and a run on them."""
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture
    from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character

    root = tmp_path_factory.mktemp("portable")
    character = make_procedural_character(ProceduralConfig(root / "char", seed=3, target_faces=600, texture_size=64))
    synthesize_capture(root / "subject", SynthConfig(num_frames=2, num_test_frames=1, num_cameras=3, width=24,
                                                     height=24, test_cameras=(2,), seed=2, character=str(character)))
    shutil.rmtree(root / "char")  # the subject holds its own copy of the character
    convert(root / "subject", root / "shards", ConvertConfig(atlas_res=32, progress=False))
    assert main(["train", str(root / "shards"), "--out", str(root / "run"), *TRAIN]) == 0
    return {"root": root, "subject": root / "subject", "shards": root / "shards", "run": root / "run"}


def test_train_refuses_an_existing_run_unless_resume_or_overwrite(rel_reference, rel_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(rel_run, run)
    before = _digest(run)
    _refused(capsys, ["train", rel_reference, "--out", run, *TRAIN], "--resume")
    assert _digest(run) == before
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("a week of work")
    for extra in ([], ["--overwrite"], ["--resume"]):
        _refused(capsys, ["train", rel_reference, "--out", mine, *TRAIN, *extra], "not a training run")
    assert (mine / "notes.txt").read_text() == "a week of work" and len(list(mine.iterdir())) == 1
    (run / "stale.txt").write_text("x")
    assert main(["train", str(rel_reference), "--out", str(run), *TRAIN, "--overwrite"]) == 0
    assert not (run / "stale.txt").exists() and (run / "capture.avatar").is_file()


def test_identity_mismatches_are_refused_naming_both_sides(rel_reference, rel_run, portable, tmp_path, capsys):
    _refused(capsys, ["eval", rel_run, "--shards", portable["shards"]], "another character")
    run = tmp_path / "run"
    shutil.copytree(rel_run, run)
    before = _digest(run)
    for shards in (portable["shards"],):
        assert main(["train", str(shards), "--out", str(run), *TRAIN, "--iters", "3", "--resume"]) == 2
        err = capsys.readouterr().err
        assert "another character" in err and str(run) in err and str(shards) in err
    assert _digest(run) == before


def test_check_identity_names_another_capture():
    from deliffas.engine.identity import CAPTURE_KEYS, IdentityError, check_identity

    a = {"character_sha256": "c" * 64, "atlas_sha256": "a" * 64, "cameras_sha256": "1" * 64}
    check_identity(a, "run", dict(a, cameras_sha256="2" * 64), "shards")  # rendering needs the same character only
    with pytest.raises(IdentityError, match="another capture .*222222222222.*111111111111"):
        check_identity(a, "run", dict(a, cameras_sha256="2" * 64), "shards", CAPTURE_KEYS)


@pytest.mark.parametrize("argv, match", [
    (["train", "s", "--out", "r", "--iters", "0"], "expected a number >= 1"),
    (["train", "s", "--out", "r", "--iters", "-5"], "expected a number >= 1"),
    (["train", "s", "--out", "r", "--device", "gpu"], "expected cpu, cuda or cuda:N"),
    (["render", "r", "--out", "x.gif"], "expected a .mp4 or .avi file"),
    (["render", "r", "--out", "x.mp4", "--frames", "0"], "expected a number >= 1"),
    (["render", "r", "--out", "x.mp4", "--fps", "0"], "positive finite number"),
    (["export", "r", "x.zip"], "ending in .avatar"),
])
def test_bad_values_are_refused_at_parse_time(capsys, argv, match):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err


@pytest.mark.parametrize("extra, match", [(["--model", "three_surface"], "model: unknown 'three_surface'"),
                                          (["--preset", "huge"], "has no preset 'huge'")])
def test_unknown_model_or_preset_is_one_error_line(rel_reference, tmp_path, capsys, extra, match):
    _refused(capsys, ["train", rel_reference, "--out", tmp_path / "run", *TRAIN, *extra], match)
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_cuda_is_the_same_error_everywhere(rel_reference, rel_run, tmp_path, capsys):
    for argv in (["train", rel_reference, "--out", tmp_path / "run", *TRAIN, "--device", "cuda"],
                 ["eval", rel_run, "--device", "cuda"],
                 ["render", rel_run, "--out", tmp_path / "v.mp4", "--device", "cuda:1"]):
        _refused(capsys, argv, "CUDA is not available on this machine")
    assert not any(tmp_path.iterdir())


def test_render_and_export_refuse_existing_outputs_and_short_motions(rel_run, tmp_path, capsys):
    video, avatar = tmp_path / "mine.mp4", tmp_path / "mine.avatar"
    video.write_bytes(b"a video of mine")
    avatar.write_bytes(b"an avatar of mine")
    _refused(capsys, ["render", rel_run, "--out", video], "pass --overwrite")
    _refused(capsys, ["export", rel_run, avatar], "pass --overwrite")
    assert video.read_bytes() == b"a video of mine" and avatar.read_bytes() == b"an avatar of mine"
    _refused(capsys, ["render", rel_run, "--out", tmp_path / "v.mp4", "--frames", "50"], "pass --loop")
    _refused(capsys, ["render", rel_run, "--out", tmp_path / "v.mp4", "--camera", "9"], "not a capture camera")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.avatar", "mine.mp4"]


@pytest.mark.parametrize("damage, match", [
    ("K", "camera 1 K: expected positive focal lengths"),
    ("K_row", "camera 0 K: expected the last row (0, 0, 1)"),
    ("atlas", "the model's atlas side 64 differs from its capture's 32"),
    ("capture", "holds no model"),
])
def test_loading_refuses_damaged_records_naming_the_file(portable, tmp_path, capsys, damage, match):
    """An avatar whose cameras cannot project, whose model config no longer fits its capture, or a run's capture
    record given as an avatar: one error line naming the file, before any work."""
    from deliffas.io.avatar_file import read_avatar_file, write_avatar_file

    avatar = tmp_path / "a.avatar"
    assert main(["export", str(portable["run"]), str(avatar)]) == 0
    f = read_avatar_file(portable["run"] / "capture.avatar" if damage == "capture" else avatar)
    arrays, record = dict(f.arrays), dict(f.record)
    if damage == "K":
        arrays["K"] = arrays["K"].copy()
        arrays["K"][1, 0, 0] = -arrays["K"][1, 0, 0]
    elif damage == "K_row":
        arrays["K"] = arrays["K"].copy()
        arrays["K"][0, 2] = (0, 1, 1)
    elif damage == "atlas":
        record["model"] = dict(record["model"], atlas_res=64)
    damaged = tmp_path / "damaged.avatar"
    write_avatar_file(damaged, arrays, record)
    capsys.readouterr()
    _refused(capsys, ["render", damaged, "--camera", "0", "--out", tmp_path / "x.mp4"], f"damaged.avatar: {match}")
    assert not (tmp_path / "x.mp4").exists()


def test_render_verbose_names_the_render_path(portable, tmp_path, caplog):
    import logging

    with caplog.at_level(logging.INFO, logger="deliffas.engine.render"):
        assert main(["-v", "render", str(portable["run"]), "--camera", "0", "--frames", "1",
                     "--out", str(tmp_path / "one")]) == 0
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("render path: ")]
    assert len(lines) == 1 and lines[0].startswith("render path: fast path, rasterised uvs"), lines


def test_export_then_render_after_shards_and_subject_are_deleted(portable, tmp_path, monkeypatch, capsys):
    """Runs last in this file: it deletes the portable capture."""
    from deliffas.io.avatar_file import read_avatar_file
    from deliffas.io.video import read_video_info

    monkeypatch.setenv("DELIFFAS_CACHE", str(tmp_path / "cache"))
    motion = tmp_path / "walk.motion"
    shutil.copyfile(next((portable["subject"] / "testing").glob("*.motion")), motion)
    avatar = tmp_path / "share" / "alice.avatar"
    assert main(["export", str(portable["run"]), str(avatar)]) == 0
    record = read_avatar_file(avatar).record
    assert record["kind"] == "avatar" and record["identity"]["character_sha256"]
    shutil.rmtree(portable["shards"])
    shutil.rmtree(portable["subject"])
    video = tmp_path / "orbit.mp4"
    assert main(["render", str(avatar), "--motion", str(motion), "--orbit", "--out", str(video),
                 "--frames", "3", "--loop"]) == 0
    info = read_video_info(video)
    assert info["codec"] == "h264" and info["frames"] == 3
    assert main(["render", str(portable["run"]), "--motion", str(motion), "--camera", "1",
                 "--out", str(tmp_path / "cam1.mp4")]) == 0
    capsys.readouterr()
    _refused(capsys, ["eval", portable["run"]], "pass --shards")
    assert main(["zoo", "list", str(tmp_path / "share")]) == 0
    assert "alice.avatar: two_surface_reflect_texture (tiny)" in capsys.readouterr().out  # the default model


def test_render_refuses_nan_weights_and_non_finite_colours(rel_run, tmp_path, capsys, monkeypatch):
    """An .avatar whose NaN weight has a valid sha256 (a buggy export) is refused on loading; a model that shades
    NaN anyway is refused by render before a frame is written."""
    import json

    import numpy as np
    from safetensors.numpy import save

    from deliffas.engine import render as render_mod
    from deliffas.io.avatar_file import AVATAR_FORMAT, AVATAR_VERSION, _array_sha256, read_avatar_file

    monkeypatch.setenv("DELIFFAS_CACHE", str(tmp_path / "cache"))
    good = tmp_path / "good.avatar"
    assert main(["export", str(rel_run), str(good)]) == 0
    f = read_avatar_file(good)
    arrays = dict(f.arrays)
    name = next(k for k in sorted(arrays) if k.startswith("model/") and arrays[k].dtype.kind == "f")
    arrays[name] = arrays[name].copy()
    arrays[name].flat[0] = np.nan
    bad = tmp_path / "bad.avatar"
    bad.write_bytes(save(arrays, metadata={"format": AVATAR_FORMAT, "version": str(AVATAR_VERSION),
                                           "record": json.dumps(f.record),
                                           "sha256": json.dumps({k: _array_sha256(v) for k, v in arrays.items()})}))
    capsys.readouterr()
    _refused(capsys, ["render", bad, "--out", tmp_path / "v.mp4", "--frames", "2"], f"array {name!r} holds 1 NaN/inf")
    load = render_mod.load_avatar

    def poisoned(*args, **kwargs):
        model, record, meta = load(*args, **kwargs)
        with torch.no_grad():
            for p in model.parameters():
                p.fill_(float("nan"))
        return model, record, meta

    monkeypatch.setattr(render_mod, "load_avatar", poisoned)
    assert main(["render", str(good), "--out", str(tmp_path / "v.mp4"), "--frames", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # the progress bar, then one error line
    assert "error: render: frame 0" in err[-1] and "non-finite values" in err[-1] and "Traceback" not in err[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.avatar", "cache", "good.avatar"]
