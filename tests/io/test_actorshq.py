"""ActorsHQ calibration.csv: normalised intrinsics, camera-to-world metres, +0.5 pixel centres pinned by HumanRF's projection."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture_cameras import POINTS_MM
from deliffas.io.formats.actorshq import actorshq_mask_path, actorshq_rgb_path, actorshq_to_camera, read_actorshq_calibration
from deliffas.io.infra.reader_checks import CaptureFormatError

HEADER = "name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py\r\n"
ROW = ["Cam007", "1022", "1372", "0.3", "2.9", "-0.2", "0.4", "1.1", "3.2", "1.21", "0.905", "0.503", "0.497"]


def test_projection_matches_humanrf(tmp_path):
    (tmp_path / "calibration.csv").write_text(HEADER + ",".join(ROW) + "\r\n")
    (c,) = read_actorshq_calibration(tmp_path)
    cam = actorshq_to_camera(c)
    w, h = 1022, 1372
    K = np.array([[1.21 * w, 0, 0.503 * w], [0, 0.905 * h, 0.497 * h], [0, 0, 1]])  # CameraData.intrinsic_matrix
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_rotvec([0.3, 2.9, -0.2]).as_matrix()  # camera -> world, metres
    c2w[:3, 3] = [0.4, 1.1, 3.2]
    P = K @ np.linalg.inv(c2w)[:3]  # projection_matrix_world2pixel
    x = np.c_[POINTS_MM / 1000.0, np.ones(len(POINTS_MM))] @ P.T
    theirs = x[:, :2] / x[:, 2:]
    ours, _ = cam.project(POINTS_MM)
    assert np.abs(ours - theirs).max() < 1e-6  # HumanRF samples at +0.5, like deliffas: no shift
    assert actorshq_rgb_path("r", "Cam007", 3).as_posix() == "r/rgbs/Cam007/Cam007_rgb000003.jpg"
    assert actorshq_mask_path("r", "Cam007", 3).as_posix() == "r/masks/Cam007/Cam007_mask000003.png"


@pytest.mark.parametrize("case,pattern", [
    ("no column", r"calibration\.csv: header column py: missing"),
    ("truncated", r"calibration\.csv: row 1: fy: missing \(the row is short or truncated\)"),
    ("text", r"calibration\.csv: row 1: tx: expected a number, got 'abc'"),
    ("nan", r"calibration\.csv: row 1: tx/ty/tz: expected finite numbers"),
    ("size", r"calibration\.csv: row 1: w/h: expected a positive integer image size"),
    ("empty", r"calibration\.csv: rows: expected at least one camera row"),
])
def test_malformed(tmp_path, case, pattern):
    row = list(ROW)
    header = HEADER
    if case == "no column":
        header = HEADER.replace(",py", "")
    elif case == "text":
        row[6] = "abc"
    elif case == "nan":
        row[6] = "nan"
    elif case == "size":
        row[1] = "0"
    text = header + ("" if case == "empty" else ",".join(row) + "\r\n")
    if case == "truncated":
        text = text[: text.index("0.905")]
    (tmp_path / "calibration.csv").write_text(text)
    with pytest.raises(CaptureFormatError, match=pattern):
        read_actorshq_calibration(tmp_path / "calibration.csv")
