"""Qualisys ``.qca.txt`` as Pose2Sim reads it: round trip, the sensor-unit and axis conventions, the real
Pose2Sim demo calibration read and checked for plausibility."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from capture_cameras import assert_same_cameras, rig
from deliffas.io.camera_formats import detect_camera_format, read_cameras, write_cameras
from deliffas.io.infra.reader_checks import CaptureFormatError

REAL = Path(__file__).resolve().parents[3] / "shared" / "real-captures" / "pose2sim-demo" / "calibration" / "Calib.qca.txt"

ONE = """<?xml version='1.0' encoding='ASCII'?>
<calibration type="regular"><cameras>
  <camera active="1" model="Miqus Video" serial="cam_2">
    <fov_video left="8" top="0" right="1087" bottom="1919"/>
    <transform r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0" x="100" y="-3000" z="1500"/>
    <intrinsic focalLengthU="64000" focalLengthV="64064" centerPointU="35328" centerPointV="61440" skew="0"
      radialDistortion1="-3.2" radialDistortion2="0.64" radialDistortion3="0" tangentalDistortion1="0.064"
      tangentalDistortion2="0"/>
  </camera>
  <camera active="1" model="Oqus 700+" serial="marker_1">
    <fov_video left="0" top="0" right="1" bottom="1"/>
  </camera>
</cameras></calibration>
"""


def test_round_trip_with_distortion(tmp_path):
    cams = rig("full")
    out = write_cameras(cams, tmp_path / "Calib.qca.txt", "qualisys")
    assert detect_camera_format(out) == "qualisys" and detect_camera_format(tmp_path) == "qualisys"
    assert_same_cameras(cams, read_cameras(out))


def test_sensor_units_axes_and_centre(tmp_path):
    """64 sensor units per pixel, fov offset, Qualisys camera axes (y up, -z forward), centre = (x, y, z) mm."""
    (tmp_path / "one.qca.txt").write_text(ONE)
    [cam] = read_cameras(tmp_path / "one.qca.txt")  # the marker camera is left out
    assert (cam.name, cam.width, cam.height) == ("cam_2", 1080, 1920)
    np.testing.assert_allclose(cam.K, [[1000, 0, 552 - 8 + 0.5], [0, 1001, 960 + 0.5], [0, 0, 1]])
    np.testing.assert_allclose(cam.center, [100, -3000, 1500], atol=1e-9)
    np.testing.assert_allclose(cam.extra["distortion"], [-0.05, 0.01, 0.001, 0, 0])
    # M's rows are the Qualisys camera axes in the world: x = world x, y (up) = world z, -z (forward) = world +y
    pix, depth = cam.project(np.array([[100.0, 0.0, 1500.0], [100.0, 0.0, 1600.0]]))
    np.testing.assert_allclose(depth, [3000, 3000])
    np.testing.assert_allclose(pix[0], [544.5, 960.5])  # straight ahead: the principal point
    assert pix[1][1] < pix[0][1]  # 10 cm higher in the z-up world is higher in the image (smaller row)


def test_skew_and_bad_numbers_are_refused(tmp_path):
    (tmp_path / "s.qca.txt").write_text(ONE.replace('skew="0"', 'skew="0.5"'))
    with pytest.raises(CaptureFormatError, match=r"s.qca.txt: camera cam_2 intrinsic.skew: expected 0"):
        read_cameras(tmp_path / "s.qca.txt")
    (tmp_path / "b.qca.txt").write_text(ONE.replace('x="100"', 'x="abc"'))
    with pytest.raises(CaptureFormatError, match=r"b.qca.txt: camera cam_2 transform: expected numbers"):
        read_cameras(tmp_path / "b.qca.txt")


@pytest.mark.skipif(not REAL.is_file(), reason="the Pose2Sim demo capture is not at ../shared/real-captures/")
def test_the_real_pose2sim_demo_calibration_is_plausible():
    """Four portrait cameras about 2 m high, 2-4.5 m around the treadmill, all seeing a point 0.9 m above it."""
    cams = read_cameras(REAL)
    assert [c.name for c in cams] == ["cam01", "cam02", "cam03", "cam04"]
    for c in cams:
        assert (c.width, c.height) == (1088, 1920)
        assert 1500 < c.K[0, 0] < 1800 and abs(c.K[0, 0] - c.K[1, 1]) < 0.01 * c.K[0, 0]
        assert 0.4 * c.width < c.K[0, 2] < 0.6 * c.width and 0.4 * c.height < c.K[1, 2] < 0.6 * c.height
        assert 2000 < np.linalg.norm(c.center[:2]) < 4500 and 1600 < c.center[2] < 2200  # mm, z up
        assert np.allclose(c.R @ c.R.T, np.eye(3), atol=1e-6) and np.linalg.det(c.R) > 0
        assert np.abs(c.extra["distortion"]).max() < 0.01
        pix, depth = c.project(np.array([[0.0, 0.0, 900.0]]))
        assert depth[0] > 2000 and 0 < pix[0, 0] < c.width and 0 < pix[0, 1] < c.height, (c.name, pix, depth)
        up, _ = c.project(np.array([[0.0, 0.0, 1400.0]]))
        assert up[0, 1] < pix[0, 1]  # higher in the world is higher in the image


def test_an_unknown_xml_encoding_is_refused_naming_the_file(tmp_path):
    """Found by the soak: an XML declaration naming an unknown encoding raised LookupError."""
    body = ONE.split("?>", 1)[-1] if ONE.lstrip().startswith("<?xml") else ONE
    (tmp_path / "e.qca.txt").write_text('<?xml version="1.0" encoding="ttf-8"?>\n' + body)
    with pytest.raises(CaptureFormatError, match=r"e.qca.txt: file: expected Qualisys XML"):
        read_cameras(tmp_path / "e.qca.txt", fmt="qualisys")
