"""``deliffas cameras``: every format and back through the CLI, and every bad input one error line (exit 2)."""

from __future__ import annotations

import hashlib
from dataclasses import replace as dataclasses_replace

import numpy as np
import pytest

from capture_cameras import HEIGHT, WIDTH, assert_same_cameras, rig
from deliffas.cli import build_parser, main
from deliffas.io.formats.dynacap.calibration import read_calibration, write_calibration
from deliffas.io.camera_formats import camera_format_names
from deliffas.io.cameras import Camera
from deliffas.io.format_registry import capture_format


def test_the_parser_knows_every_format():
    cameras = build_parser()._subparsers._group_actions[0].choices["cameras"]
    to = next(a for a in cameras._actions if a.dest == "to_format")
    assert tuple(to.choices) == camera_format_names()


@pytest.mark.parametrize("fmt", camera_format_names())
def test_dynacap_to_every_format_and_back(tmp_path, fmt, capsys):
    cams = rig()
    write_calibration(tmp_path / "src.calibration", cams)
    out = tmp_path / fmt / capture_format(fmt).camera_path
    assert main(["cameras", str(tmp_path / "src.calibration"), str(out), "--to", fmt]) == 0
    size = ["--size", f"{WIDTH}x{HEIGHT}"]
    assert main(["cameras", str(out), str(tmp_path / "back.calibration"), "--to", "dynacap", "--from", fmt, *size]) == 0
    assert_same_cameras(read_calibration(tmp_path / "back.calibration"), cams)
    assert "wrote 5 cameras" in capsys.readouterr().out


def test_colmap_shorthands(tmp_path):
    cams = rig()
    write_calibration(tmp_path / "src.calibration", cams)
    assert main(["cameras", str(tmp_path / "src.calibration"), "--to-colmap", str(tmp_path / "m"), "--text"]) == 0
    assert (tmp_path / "m" / "cameras.txt").is_file()
    assert main(["cameras", str(tmp_path / "back.calibration"), "--from-colmap", str(tmp_path / "m")]) == 0
    assert_same_cameras(read_calibration(tmp_path / "back.calibration"), cams)


def test_the_api_takes_the_commands_config(tmp_path):
    """``convert_cameras(CamerasConfig(...))`` is ``deliffas cameras`` (shorthands resolved the same way)."""
    from deliffas.io.camera_formats import CamerasConfig, convert_cameras

    write_calibration(tmp_path / "src.calibration", rig())
    done = convert_cameras(CamerasConfig(tmp_path / "src.calibration", to_colmap=tmp_path / "m", text=True))
    assert (done.count, done.fmt) == (5, "colmap") and (tmp_path / "m" / "cameras.txt").is_file()
    back = convert_cameras(CamerasConfig(tmp_path / "back.calibration", from_colmap=tmp_path / "m"))
    assert back.fmt == "dynacap" and back.path == tmp_path / "back.calibration"
    assert_same_cameras(read_calibration(back.path), rig())
    with pytest.raises(ValueError, match="not both"):
        convert_cameras(CamerasConfig(tmp_path / "src.calibration", to_colmap=tmp_path / "m",
                                      from_colmap=tmp_path / "m"))


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def _fails(capsys, argv, match):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("deliffas cameras: error:") and match in err[0], err


def test_bad_inputs_are_one_error_line(tmp_path, capsys):
    cams = rig()
    write_calibration(tmp_path / "src.calibration", cams)
    skew = Camera("s", np.array([[100.0, 2.0, 32], [0, 100, 24], [0, 0, 1]]), np.eye(4), 64, 48)
    write_calibration(tmp_path / "skew.calibration", [skew])
    _fails(capsys, ["cameras", str(tmp_path / "skew.calibration"), str(tmp_path / "m"), "--to", "colmap"], "skew")
    (tmp_path / "empty").mkdir()
    _fails(capsys, ["cameras", str(tmp_path / "x.calibration"), "--from-colmap", str(tmp_path / "empty")],
           "not a COLMAP model")
    (tmp_path / "garbage").mkdir()
    (tmp_path / "garbage" / "cameras.bin").write_bytes(b"\x00garbage" * 10)
    (tmp_path / "garbage" / "images.bin").write_bytes(b"\x00garbage" * 10)
    _fails(capsys, ["cameras", str(tmp_path / "x.calibration"), "--from-colmap", str(tmp_path / "garbage")],
           "cameras.bin: count: ")
    assert main(["cameras", str(tmp_path / "src.calibration"), str(tmp_path / "a.npy"), "--to", "zju"]) == 0
    capsys.readouterr()
    _fails(capsys, ["cameras", str(tmp_path / "a.npy"), str(tmp_path / "b.calibration"), "--to", "dynacap"],
           "size")
    _fails(capsys, ["cameras", str(tmp_path / "src.calibration")], "--to FORMAT")
    before = _digest(tmp_path)
    _fails(capsys, ["cameras", str(tmp_path / "src.calibration"), str(tmp_path / "skew.calibration"), "--to",
                    "dynacap"], "--overwrite")
    assert _digest(tmp_path) == before
    with pytest.raises(SystemExit) as info:
        main(["cameras", str(tmp_path / "src.calibration"), str(tmp_path / "o"), "--to", "blender"])
    assert info.value.code == 2


def test_shorthands_come_from_the_registry():
    """Each ``--to-NAME`` / ``--from-NAME`` field of the config is a registered format's shorthand, and back."""
    import dataclasses

    from deliffas.io.camera_formats import CamerasConfig, shorthand_fields

    fields = {f.name for f in dataclasses.fields(CamerasConfig) if f.name.startswith(("to_", "from_"))}
    assert fields - {"to_format", "from_format"} == set(shorthand_fields())
    for key, (direction, name) in shorthand_fields().items():
        assert key == f"{direction}_{name}" and capture_format(name).shorthand_with in camera_format_names()


def test_text_is_refused_for_a_format_without_a_text_variant(tmp_path, capsys):
    write_calibration(tmp_path / "src.calibration", rig())
    _fails(capsys, ["cameras", str(tmp_path / "src.calibration"), str(tmp_path / "a.npy"), "--to", "zju", "--text"],
           "zju has no text variant (formats with one: colmap)")
    assert not (tmp_path / "a.npy").exists()


def test_lossy_distortion_names_the_flag_on_the_cli_and_the_argument_in_python(tmp_path, capsys):
    from deliffas.io.camera_conventions import LossyConversionError
    from deliffas.io.camera_formats import CamerasConfig, convert_cameras

    write_calibration(tmp_path / "src.calibration", [dataclasses_replace(c, radial=0.01) for c in rig()])
    argv = ["cameras", str(tmp_path / "src.calibration"), str(tmp_path / "m"), "--to", "colmap"]
    _fails(capsys, argv, "undistort the images first, or pass --drop-distortion")
    with pytest.raises(LossyConversionError, match=r"or pass drop_distortion=True$"):
        convert_cameras(CamerasConfig(tmp_path / "src.calibration", tmp_path / "m", to_format="colmap"))
    assert main([*argv, "--drop-distortion"]) == 0


def test_undetectable_source_names_from_on_the_cli_and_fmt_in_python(tmp_path, capsys):
    from deliffas.io.camera_formats import CamerasConfig, convert_cameras

    src = tmp_path / "rig.unknown"
    src.write_text("not a camera file\n")
    _fails(capsys, ["cameras", str(src), str(tmp_path / "m"), "--to", "colmap"], "pass --from FORMAT (one of ")
    with pytest.raises(ValueError, match=r"pass fmt= \(one of "):
        convert_cameras(CamerasConfig(src, tmp_path / "m", to_format="colmap"))
