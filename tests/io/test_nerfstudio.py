"""nerfstudio transforms.json: OpenGL camera-to-world pinned by a hand projection (y up, -z forward, +0.5 pixels)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture_cameras import POINTS_MM
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.formats.nerfstudio import nerfstudio_to_camera, read_transforms

A = 0.4
C2W = [[np.cos(A), 0, np.sin(A), 1.2], [0, 1, 0, 0.9], [-np.sin(A), 0, np.cos(A), 3.1], [0, 0, 0, 1]]


def _meta(**frame):
    f = {"file_path": "images/frame_00001.png", "transform_matrix": C2W}
    f.update(frame)
    return {"fl_x": 700.0, "fl_y": 690.0, "cx": 319.5, "cy": 242.25, "w": 640, "h": 480, "frames": [f]}


def test_projection_matches_opengl_convention(tmp_path):
    (tmp_path / "transforms.json").write_text(json.dumps(_meta()))
    (fr,) = read_transforms(tmp_path)
    cam = nerfstudio_to_camera(fr)
    assert cam.name == "frame_00001"
    X = np.c_[POINTS_MM / 1000.0, np.ones(len(POINTS_MM))]
    x, y, z = (X @ np.linalg.inv(np.array(C2W)).T)[:, :3].T  # OpenGL camera: looks along -z, y up
    assert (z < 0).all()
    theirs = np.stack([700.0 * x / -z + 319.5, 690.0 * -y / -z + 242.25], axis=1)  # row grows downwards
    ours, _ = cam.project(POINTS_MM)
    assert np.abs(ours - theirs).max() < 1e-6  # nerfstudio's pixel_offset=0.5 is deliffas': no shift


def test_per_frame_values_win_and_k4_is_refused(tmp_path):
    (tmp_path / "t.json").write_text(json.dumps(_meta(fl_x=800.0, k1=0.1)))
    (fr,) = read_transforms(tmp_path / "t.json")
    assert fr.fl_x == 800.0 and fr.fl_y == 690.0 and fr.distortion[0] == 0.1
    (tmp_path / "k4.json").write_text(json.dumps(_meta(k4=0.01)))
    with pytest.raises(CaptureFormatError, match=r"k4\.json: frames\[0\]\.k4: expected 0"):
        read_transforms(tmp_path / "k4.json")


@pytest.mark.parametrize("frame,top,pattern", [
    ({}, "fl_x", r"t\.json: frames\[0\]\.fl_x: missing \(in the frame and at the top level\)"),
    ({"transform_matrix": C2W[:3]}, None, r"t\.json: frames\[0\]\.transform_matrix: expected shape \(4, 4\), got \(3, 4\)"),
    ({"transform_matrix": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, None,
     r"t\.json: frames\[0\]\.transform_matrix: expected a rotation"),
    ({"cx": float("nan")}, None, r"t\.json: frames\[0\]\.fl_x/fl_y/cx/cy: expected finite numbers"),
    ({}, "frames", r"t\.json: frames: missing"),
    ("truncated", None, r"t\.json: JSON line \d+: expected valid JSON"),
])
def test_malformed(tmp_path, frame, top, pattern):
    path = tmp_path / "t.json"
    if frame == "truncated":
        path.write_text(json.dumps(_meta())[:-30])
    else:
        meta = _meta(**frame)
        meta.pop(top, None)
        path.write_text(json.dumps(meta))
    with pytest.raises(CaptureFormatError, match=pattern):
        read_transforms(path)
