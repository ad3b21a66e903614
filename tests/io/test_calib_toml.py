"""Pose2Sim / anipose ``Calib.toml``: round trip, the OpenCV convention (centre, projection), refusals."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from capture_cameras import assert_same_cameras, rig
from deliffas.io.camera_formats import detect_camera_format, read_cameras, write_cameras
from deliffas.io.infra.reader_checks import CaptureFormatError

CALIB = """
[cam_1]
name = "cam01"
size = [ 1088.0, 1920.0,]
matrix = [ [ 1681.2, 0.0, 532.9,], [ 0.0, 1681.0, 948.1,], [ 0.0, 0.0, 1.0,],]
distortions = [ 0.0, 0.0, 0.0, 0.0,]
rotation = [ 1.2, -0.3, 0.4,]
translation = [ 0.25, -0.4, 3.1,]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"""


def test_round_trip_with_distortion(tmp_path):
    cams = rig("full")
    out = write_cameras(cams, tmp_path / "Calib.toml", "pose2sim")
    assert detect_camera_format(out) == "pose2sim" and detect_camera_format(tmp_path) == "pose2sim"
    assert_same_cameras(cams, read_cameras(out))


def test_opencv_pose_in_metres_and_integer_pixel_centres(tmp_path):
    """The file's rvec/t (m) and K project a point as cv2.projectPoints does, half a pixel apart."""
    (tmp_path / "Calib.toml").write_text(CALIB)
    cam = read_cameras(tmp_path / "Calib.toml")[0]
    rvec, t = np.array([1.2, -0.3, 0.4]), np.array([0.25, -0.4, 3.1])
    R = cv2.Rodrigues(rvec)[0]
    np.testing.assert_allclose(cam.center, -R.T @ t * 1000, rtol=1e-12)  # mm
    point_m = np.array([[0.1, 0.2, 0.3]])
    K = np.array([[1681.2, 0, 532.9], [0, 1681.0, 948.1], [0, 0, 1]])
    expected, _ = cv2.projectPoints(point_m, rvec, t, K, np.zeros(4))
    pix, depth = cam.project(point_m * 1000)
    np.testing.assert_allclose(pix[0], expected.ravel() + 0.5, atol=1e-9)
    assert depth[0] > 0 and (cam.name, cam.width, cam.height) == ("cam01", 1088, 1920)


def test_millimetre_files_and_fisheye_are_refused(tmp_path):
    (tmp_path / "mm.toml").write_text(CALIB.replace("[ 0.25, -0.4, 3.1,]", "[ 250.0, -400.0, 3100.0,]"))
    with pytest.raises(CaptureFormatError, match=r"mm.toml: cam_1.translation: expected metres .*divide"):
        read_cameras(tmp_path / "mm.toml", "pose2sim")
    (tmp_path / "fish.toml").write_text(CALIB.replace("fisheye = false", "fisheye = true"))
    with pytest.raises(CaptureFormatError, match="cam_1.fisheye: fisheye lenses are not supported"):
        read_cameras(tmp_path / "fish.toml", "pose2sim")
