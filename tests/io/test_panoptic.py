"""CMU Panoptic ``calibration_<seq>.json``: round trip, centimetres, the OpenCV projection of the toolbox."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture_cameras import assert_same_cameras, rig
from deliffas.io.camera_formats import detect_camera_format, read_cameras, write_cameras
from deliffas.io.infra.reader_checks import CaptureFormatError

R = [[0.9, 0.0, -0.43588989435406733], [0.0, 1.0, 0.0], [0.43588989435406733, 0.0, 0.9]]
CAMERA = {"name": "00_03", "type": "hd", "resolution": [1920, 1080], "panel": 0, "node": 3,
          "K": [[1634.0, 0.0, 942.0], [0.0, 1630.0, 552.0], [0.0, 0.0, 1.0]],
          "distCoef": [0.0, 0.0, 0.0, 0.0, 0.0], "R": R, "t": [[-12.0], [110.0], [290.0]]}


def _toolbox_project(X_cm: np.ndarray, cam: dict) -> np.ndarray:
    """The toolbox's projection without distortion: x = R X + t, divided by z, times K (OpenCV pixels)."""
    x = np.asarray(cam["R"]) @ X_cm + np.ravel(cam["t"])
    return (np.asarray(cam["K"]) @ (x / x[2]))[:2]


def test_round_trip_with_distortion(tmp_path):
    cams = rig("full")
    out = write_cameras(cams, tmp_path / "calibration_seq.json", "panoptic")
    assert detect_camera_format(out) == "panoptic" and detect_camera_format(tmp_path) == "panoptic"
    assert_same_cameras(cams, read_cameras(out))


def test_centimetres_and_projection_of_a_known_point(tmp_path):
    (tmp_path / "calibration_171204_pose1.json").write_text(json.dumps({"cameras": [CAMERA]}))
    [cam] = read_cameras(tmp_path)
    assert (cam.name, cam.width, cam.height) == ("00_03", 1920, 1080)
    np.testing.assert_allclose(cam.center, -np.asarray(R).T @ np.array([-12.0, 110.0, 290.0]) * 10, rtol=1e-12)
    X_cm = np.array([20.0, -80.0, 15.0])
    pix, depth = cam.project(X_cm[None] * 10)  # mm
    np.testing.assert_allclose(pix[0], _toolbox_project(X_cm, CAMERA) + 0.5, atol=1e-9)
    assert depth[0] > 0


def test_bad_cameras_are_named(tmp_path):
    bad = dict(CAMERA, t=[[1.0], [2.0]])
    (tmp_path / "calibration_x.json").write_text(json.dumps({"cameras": [bad]}))
    with pytest.raises(CaptureFormatError, match=r"calibration_x.json: camera 00_03.t: "):
        read_cameras(tmp_path / "calibration_x.json")
    (tmp_path / "calibration_y.json").write_text(json.dumps({"cameras": []}))
    with pytest.raises(CaptureFormatError, match="cameras: expected a non-empty list"):
        read_cameras(tmp_path / "calibration_y.json", "panoptic")
