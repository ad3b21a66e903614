"""Every camera reader refuses what no real camera can be (``check_camera``), duplicate keys and names, and lens
models deliffas cannot represent, naming the file, the key and the value (issue 32, items 1-4)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from capture_cameras import rig
from deliffas.io.camera_formats import read_cameras, write_cameras
from deliffas.io.format_registry import capture_format

SIZE = (160, 120)


def _written(tmp_path: Path, fmt: str) -> Path:
    out = tmp_path / fmt
    out.mkdir()
    text = capture_format(fmt).text_variant is not None  # the text variant where there is one (COLMAP's .txt)
    return write_cameras(rig(), out / "x.calibration" if fmt == "dynacap" else out, fmt, text=text)


def _sub(p: Path, old: str, new: str) -> None:
    text = p.read_text()
    assert old in text, (p, old)
    p.write_text(text.replace(old, new, 1))


def _edit_json(p: Path, edit) -> None:
    data = json.loads(p.read_text())
    edit(data)
    p.write_text(json.dumps(data))


def _refused(path: Path, fmt: str, *matches: str) -> None:
    with pytest.raises(ValueError) as err:
        read_cameras(path, fmt, size=SIZE)
    message = str(err.value)
    assert str(path.parent if path.is_file() else path) in message, message
    for m in matches:
        assert m in message, message


def _zju_edit(path: Path, edit) -> None:
    from dataclasses import replace

    from deliffas.io.formats.zju_mocap import ZjuAnnots, read_zju_annots, write_zju_annots

    annots = read_zju_annots(path)
    write_zju_annots(path, ZjuAnnots(tuple(edit(list(annots.cameras), replace)), annots.ims))


# ------------------------------------------------------------------ item 1: K's last row
@pytest.mark.parametrize("fmt", ["easymocap", "thuman4", "dynacap"])
def test_intrinsics_with_another_last_row_are_refused(tmp_path, fmt):
    p = _written(tmp_path, fmt)
    if fmt == "easymocap":
        _sub(p / "intri.yml", "0.0, 0.0, 1.0]", "0.0, 0.0, 2.0]")
    elif fmt == "thuman4":
        _edit_json(p, lambda d: d["cam0"].__setitem__("K", d["cam0"]["K"][:2] + [[0, 0, 2]]))
    else:
        _sub(p, "0.0 0.0 1.0 0.0 0.0 0.0 0.0 1.0", "0.0 0.0 2.0 0.0 0.0 0.0 0.0 1.0")
    _refused(p, fmt, "cam0", "expected the last row (0, 0, 1), got (0.0, 0.0, 2.0)")


def test_a_singular_k_is_refused_when_read_not_when_rendered(tmp_path):
    p = _written(tmp_path, "thuman4")
    _edit_json(p, lambda d: d["cam2"].__setitem__("K", d["cam2"]["K"][:2] + [[0, 0, 0]]))
    _refused(p, "thuman4", "calibration.json", "cam2", "expected the last row (0, 0, 1)")


# ------------------------------------------------------------------ item 4: implausible cameras
@pytest.mark.parametrize("fmt", ["easymocap", "zju", "nerfstudio", "actorshq", "thuman4"])
def test_negative_focal_lengths_are_refused(tmp_path, fmt):
    p = _written(tmp_path, fmt)
    if fmt == "easymocap":
        _sub(p / "intri.yml", "data: [150.0,", "data: [-150.0,")
    elif fmt == "zju":
        _zju_edit(p, lambda cams, replace: [replace(cams[0], K=cams[0].K * [[-1], [1], [1]])] + cams[1:])
    elif fmt == "nerfstudio":
        _edit_json(p, lambda d: d["frames"][0].__setitem__("fl_x", -150.0))
    elif fmt == "actorshq":
        _sub(p, ",0.9375,", ",-0.9375,")
    else:
        _edit_json(p, lambda d: d["cam0"]["K"][0].__setitem__(0, -150.0))
    _refused(p, fmt, "cam0", "expected positive focal lengths", "fx = -150")


def test_a_principal_point_far_outside_the_image_is_refused(tmp_path):
    p = _written(tmp_path, "nerfstudio")
    _edit_json(p, lambda d: d["frames"][1].__setitem__("cx", 7090.0))  # cx in the wrong unit (1/100 px)
    _refused(p, "nerfstudio", "cam1", "principal point", "7090")


# ------------------------------------------------------------------ item 3: duplicate keys and names
def test_a_duplicate_json_key_is_refused(tmp_path):
    p = _written(tmp_path, "thuman4")
    _sub(p, '"cam1"', '"cam0"')  # json.loads would keep the second cam0 and lose a camera silently
    _refused(p, "thuman4", "JSON key 'cam0'", "given twice")


@pytest.mark.parametrize("fmt", ["nerfstudio", "actorshq", "dynacap", "zju"])
def test_duplicate_camera_names_are_refused(tmp_path, fmt):
    p = _written(tmp_path, fmt)
    if fmt == "nerfstudio":
        _sub(p, "images/cam1.png", "images/cam0.png")
    elif fmt == "actorshq":
        _sub(p, "\ncam1,", "\ncam0,")
    elif fmt == "dynacap":
        _sub(p, "name          cam1", "name          cam0")
    else:  # ZJU-MoCap renamed the cameras 0..4 without a word
        _zju_edit(p, lambda cams, replace: [cams[0], replace(cams[1], name="cam0")] + cams[2:])
    _refused(p, fmt, "camera name 'cam0' appears 2 times")


def test_writers_refuse_duplicate_names(tmp_path):
    from dataclasses import replace

    cams = rig()
    cams[1] = replace(cams[1], name="cam0")
    with pytest.raises(ValueError, match="camera name 'cam0' appears 2 times"):
        write_cameras(cams, tmp_path, "nerfstudio")
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------ item 2: nerfstudio camera_model
@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "EQUIRECTANGULAR", "FISHEYE624"])
def test_nerfstudio_lens_models_deliffas_cannot_represent_are_refused(tmp_path, model):
    p = _written(tmp_path, "nerfstudio")

    def fisheye(d):
        d["camera_model"] = model
        for f in d["frames"]:
            f.update(k1=0.1, k2=0.01, k3=0.001)  # fisheye k1..k3 (k4 = 0): not OpenCV's radial terms

    _edit_json(p, fisheye)
    _refused(p, "nerfstudio", "camera_model", repr(model), "undistort")


@pytest.mark.parametrize("model", ["OPENCV", "PINHOLE", "SIMPLE_PINHOLE", None])
def test_nerfstudio_pinhole_models_are_read(tmp_path, model):
    p = _written(tmp_path, "nerfstudio")
    _edit_json(p, lambda d: d.pop("camera_model") if model is None else d.__setitem__("camera_model", model))
    assert [c.name for c in read_cameras(p)] == [c.name for c in rig()]


def test_cameras_cli_refuses_a_fisheye_transforms_json(tmp_path, capsys):
    from deliffas.cli import main

    p = _written(tmp_path, "nerfstudio")
    _edit_json(p, lambda d: d.__setitem__("camera_model", "OPENCV_FISHEYE"))
    assert main(["cameras", str(p), str(tmp_path / "out"), "--to", "easymocap"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera_model" in err[0] and "OPENCV_FISHEYE" in err[0], err
    assert not (tmp_path / "out").exists()
