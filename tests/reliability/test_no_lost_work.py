"""Commands that write never replace a user's work unasked, and bad arguments end in one error line.

Each refusal leaves every byte of what the user had unchanged (checksums before and after).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from deliffas.cli import main


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(capsys, argv, match, exit_code=2):
    assert main(argv) == exit_code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error:" in err[0] and match in err[0], err


@pytest.fixture
def users_folder(tmp_path):
    d = tmp_path / "mine"
    d.mkdir()
    (d / "thesis.tex").write_text("a day of work")
    return d


@pytest.mark.parametrize("argv", [
    ["synth", "{d}", "--frames", "1", "--cameras", "2"],
    ["synth", "{d}", "--frames", "1", "--cameras", "2", "--overwrite"],
    ["character", "procedural", "{d}"],
    ["character", "procedural", "{d}", "--overwrite"],
    ["template", "{sample}", "--out", "{d}"],
    ["convert", "{subject}", "{d}"],
])
def test_a_users_folder_is_never_replaced(users_folder, capsys, argv, tmp_path):
    before = _digest(users_folder)
    subject = tmp_path / "subject"
    subject.mkdir()
    (subject / "cameras.calibration").write_text("x")
    argv = [a.format(d=users_folder, sample=tmp_path / "none.character", subject=subject) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "error:" in err and str(users_folder) in err
    assert _digest(users_folder) == before


def test_synth_replaces_only_its_own_capture_with_overwrite(tmp_path, capsys):
    out = tmp_path / "subj"
    args = ["synth", str(out), "--frames", "1", "--test-frames", "1", "--cameras", "2", "--size", "16x16"]
    assert main(args) == 0
    before = _digest(out)
    _refused(capsys, args, "pass --overwrite")
    assert _digest(out) == before
    (out / "stale.txt").write_text("from an earlier capture")
    assert main(args + ["--overwrite", "--seed", "1"]) == 0
    assert not (out / "stale.txt").exists() and (out / "synth.json").is_file()


def test_pose_output_and_non_finite_motion(sample_dir, tmp_path, capsys):
    out = tmp_path / "p.ply"
    out.write_text("mine")
    motion = sample_dir / "skeletoolToGTPose" / "poseAngles.motion"
    _refused(capsys, ["pose", str(sample_dir / "ddc.character"), str(motion), "--out", str(out)], "--overwrite")
    assert out.read_text() == "mine"
    lines = motion.read_text().splitlines()
    vals = lines[1].split()
    vals[1] = "1e306"
    huge = tmp_path / "huge.motion"
    huge.write_text("\n".join([lines[0], " ".join(vals)]) + "\n")
    _refused(capsys, ["pose", str(sample_dir / "ddc.character"), str(huge), "--frame", vals[0],
                      "--out", str(tmp_path / "h.ply")], "non-finite vertices")
    assert not (tmp_path / "h.ply").exists()


@pytest.mark.parametrize("argv, match", [
    (["synth", "x", "--cameras", "0"], "expected a number >= 1"),
    (["synth", "x", "--frames", "-5"], "expected a number >= 1"),
    (["convert", "a", "b", "--jobs", "0"], "expected a number >= 1"),
    (["pose", "a.character", "m.motion", "--out", "x.stl"], "ending in .ply or .obj"),
])
def test_bad_values_are_refused_before_any_work(capsys, argv, match):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err
