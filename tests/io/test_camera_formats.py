"""read_cameras / write_cameras: every format pair round-trips a DynaCap rig exactly; distortion is never lost silently."""

from __future__ import annotations

import itertools
import logging

import numpy as np
import pytest

from capture_cameras import HEIGHT, WIDTH, assert_same_cameras, rig
from deliffas.io.formats.dynacap.calibration import write_calibration
from deliffas.io.camera_conventions import DISTORTION, LossyConversionError
from deliffas.io.camera_conventions import DISTORTION_NAMES
from deliffas.io.camera_formats import camera_format_names, detect_camera_format, read_cameras, write_cameras
from deliffas.io.format_registry import capture_format

SIZE = (WIDTH, HEIGHT)
CAMERA_FORMATS = camera_format_names()
FULL = tuple(f for f in CAMERA_FORMATS if capture_format(f).distortion == DISTORTION_NAMES)  # OpenCV's five
RADIAL = tuple(f for f in CAMERA_FORMATS if f not in FULL and "k1" in capture_format(f).distortion)
NO_TANGENTIAL = tuple(f for f in CAMERA_FORMATS if "p1" not in capture_format(f).distortion)


def _target(tmp_path, fmt: str, tag: str):
    """Where ``fmt`` keeps its cameras in a new capture folder ``<tag>_<fmt>``."""
    return tmp_path / f"{tag}_{fmt}" / capture_format(fmt).camera_path


@pytest.mark.parametrize("src,dst", list(itertools.product(CAMERA_FORMATS, CAMERA_FORMATS)))
def test_every_pair_round_trips(tmp_path, src, dst):
    """DynaCap rig -> src -> dst -> src -> read: equal to the original (float64 files: 1e-9)."""
    original = rig()
    write_calibration(tmp_path / "orig.calibration", original)
    start = read_cameras(tmp_path / "orig.calibration")
    a = write_cameras(start, _target(tmp_path, src, "a"), src)
    b = write_cameras(read_cameras(a, size=SIZE), _target(tmp_path, dst, "b"), dst)
    assert detect_camera_format(b) == dst
    c = write_cameras(read_cameras(b, size=SIZE), _target(tmp_path, src, "c"), src)
    assert_same_cameras(original, read_cameras(c, size=SIZE))


@pytest.mark.parametrize("src,dst", list(itertools.product(FULL, FULL)) + list(itertools.product(RADIAL, FULL)))
def test_distortion_round_trips(tmp_path, src, dst):
    original = rig("radial" if src in RADIAL else "full")
    a = write_cameras(original, _target(tmp_path, src, "a"), src)
    b = write_cameras(read_cameras(a, size=SIZE), _target(tmp_path, dst, "b"), dst)
    back = read_cameras(write_cameras(read_cameras(b, size=SIZE), _target(tmp_path, src, "c"), src), size=SIZE)
    assert_same_cameras(original, back)
    assert np.any(back[1].extra[DISTORTION] != 0)


@pytest.mark.parametrize("fmt", NO_TANGENTIAL)
def test_distortion_is_never_dropped_silently(tmp_path, fmt, caplog):
    cams = rig("full")
    with pytest.raises(LossyConversionError, match=r"camera cam0: .* cannot store lens distortion .*p1"):
        write_cameras(cams, _target(tmp_path, fmt, "x"), fmt)
    with caplog.at_level(logging.WARNING):
        out = write_cameras(cams, _target(tmp_path, fmt, "y"), fmt, drop_distortion=True)
    assert "dropped as asked" in caplog.text
    back = read_cameras(out, size=SIZE)
    kept = back[1].extra.get(DISTORTION, np.zeros(5))
    assert kept[2] == 0 and kept[3] == 0  # no format of these holds tangential terms
    held = [i for i, n in enumerate(DISTORTION_NAMES) if n in capture_format(fmt).distortion]
    assert np.allclose(kept[held], cams[1].extra[DISTORTION][held], rtol=1e-12)  # what it holds survives


def test_dynacap_radial_is_not_an_opencv_coefficient(tmp_path):
    from dataclasses import replace

    cams = [replace(c, radial=0.01) for c in rig()]
    write_cameras(cams, tmp_path / "r.calibration", "dynacap")  # DynaCap keeps its own coefficient
    assert read_cameras(tmp_path / "r.calibration")[0].radial == 0.01
    with pytest.raises(LossyConversionError, match="DynaCap radial=0.01"):
        write_cameras(cams, tmp_path / "n.json", "nerfstudio")


def test_size_is_required_where_the_format_has_none(tmp_path):
    out = write_cameras(rig(), tmp_path / "z", "zju")
    with pytest.raises(ValueError, match=r"zju camera .*holds no image to read it from; pass --size WxH"):
        read_cameras(out)
    smc = write_cameras(rig(), tmp_path / "d.smc", "dna")
    with pytest.raises(ValueError, match=r"camera 00 has no image or mask .*--size WxH"):
        read_cameras(smc)
    assert read_cameras(out, size=(64, 48))[0].width == 64


@pytest.mark.parametrize("fmt", ["zju", "easymocap"])
def test_missing_sizes_are_read_from_each_cameras_first_image(tmp_path, fmt):
    import cv2

    out = write_cameras(rig(), tmp_path / "cap", fmt)
    root = out if out.is_dir() else out.parent
    if fmt == "easymocap":  # EasyMocap's own intri.yml often has no H_/W_
        for name in ("H_", "W_"):
            text = (root / "intri.yml").read_text().splitlines()
            (root / "intri.yml").write_text("\n".join(x for x in text if not x.startswith(name)) + "\n")
    for i, c in enumerate(rig()):
        folder = root / ("images" if fmt == "easymocap" else "") / c.name
        folder.mkdir(parents=True, exist_ok=True)
        # sizes the file does not store, near the rig's own (a principal point must lie near the image)
        cv2.imwrite(str(folder / "000000.jpg"), np.zeros((c.height + 2 * i, c.width + i, 3), np.uint8))
    read = read_cameras(root)
    assert [(c.width, c.height) for c in read] == [(c.width + i, c.height + 2 * i) for i, c in enumerate(rig())]
    assert read_cameras(root, size=(64, 48))[0].width == 64  # --size stays the override


def test_detection_and_unknown_formats(tmp_path):
    (tmp_path / "x.json").write_text('{"frames": []}')
    assert detect_camera_format(tmp_path / "x.json") == "nerfstudio"
    (tmp_path / "y.json").write_text('{"cam00": {}}')
    assert detect_camera_format(tmp_path / "y.json") == "thuman4"
    with pytest.raises(ValueError, match="cannot tell the camera format"):
        detect_camera_format(tmp_path / "cams.txt")
    with pytest.raises(ValueError, match="no camera file found"):
        detect_camera_format(tmp_path)
    with pytest.raises(ValueError, match="unknown camera format 'blender'"):
        write_cameras(rig(), tmp_path / "o", "blender")
