"""THuman4.0 calibration.json: metres + OpenCV pixel centres pinned by the dataset Readme's projection; malformed files named."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture_cameras import POINTS_MM
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.formats.thuman4 import (read_thuman4_calibration, read_thuman4_smplx, thuman4_image_path, thuman4_mask_path,
                                 thuman4_to_camera)

K = [[1500.0, 0, 610.4], [0, 1498.0, 505.6], [0, 0, 1]]
A = -1.2
R = [[np.cos(A), 0, np.sin(A)], [0, 1, 0], [-np.sin(A), 0, np.cos(A)]]
T = [0.3, -0.8, 3.6]


def _entry(**over):
    e = {"K": K, "R": np.ravel(R).tolist(), "T": T, "imgSize": [1224, 1024]}  # R flat, as reshape(3, 3) allows
    e.update(over)
    return e


def test_projection_matches_the_readme(tmp_path):
    (tmp_path / "calibration.json").write_text(json.dumps({"cam00": _entry()}))
    (c,) = read_thuman4_calibration(tmp_path)
    cam = thuman4_to_camera(c)
    verts = POINTS_MM / 1000.0  # SMPL-X vertices are metres
    v_cam = verts @ np.array(R).T + np.array(T)  # Readme: smpl_verts @ cam_R^T + cam_t
    theirs = (v_cam / v_cam[:, 2:]) @ np.array(K).T  # then K; pixel centres on integers (gen_uv)
    ours, _ = cam.project(POINTS_MM)
    assert np.abs((ours - 0.5) - theirs[:, :2]).max() < 1e-6
    assert (cam.width, cam.height) == (1224, 1024)
    assert thuman4_image_path("s", "cam00", 7).as_posix() == "s/images/cam00/00000007.jpg"
    assert thuman4_mask_path("s", "cam00", 7).as_posix() == "s/masks/cam00/00000007.jpg"


def test_smplx_npz(tmp_path):
    n = 4
    np.savez(tmp_path / "smpl_params.npz", betas=np.zeros((1, 10)), global_orient=np.zeros((n, 3)),
             transl=np.ones((n, 3)), body_pose=np.zeros((n, 63)), jaw_pose=np.zeros((n, 3)))
    s = read_thuman4_smplx(tmp_path / "smpl_params.npz")
    assert s.num_frames == n and "jaw_pose" in s.others and s.transl[2, 1] == 1
    np.savez(tmp_path / "bad.npz", betas=np.zeros((1, 10)), global_orient=np.zeros((n, 3)), body_pose=np.zeros((n, 63)))
    with pytest.raises(CaptureFormatError, match=r"bad\.npz: transl: missing"):
        read_thuman4_smplx(tmp_path / "bad.npz")
    (tmp_path / "cut.npz").write_bytes((tmp_path / "smpl_params.npz").read_bytes()[:100])
    with pytest.raises(CaptureFormatError, match=r"cut\.npz: NPZ: expected an \.npz \(zip\) archive"):
        read_thuman4_smplx(tmp_path / "cut.npz")


@pytest.mark.parametrize("entry,pattern", [
    ({"K": None}, r"calibration\.json: cam00\.K: missing"),
    ({"T": [0.3, 0.1]}, r"calibration\.json: cam00\.T: expected shape \(3,\), got \(2,\)"),
    ({"K": [[1, 0, float("nan")], [0, 1, 0], [0, 0, 1]]}, r"calibration\.json: cam00\.K: expected finite numbers"),
    ({"R": [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}, r"calibration\.json: cam00\.R: expected a rotation"),
    ({"imgSize": [1224.5, 1024]}, r"calibration\.json: cam00\.imgSize: expected a positive integer image size"),
    ("truncated", r"calibration\.json: JSON line \d+: expected valid JSON"),
])
def test_malformed(tmp_path, entry, pattern):
    path = tmp_path / "calibration.json"
    if entry == "truncated":
        path.write_text(json.dumps({"cam00": _entry()})[:60])
    else:
        e = _entry(**entry)
        e = {k: v for k, v in e.items() if v is not None}
        path.write_text(json.dumps({"cam00": e}).replace("NaN", "NaN"))
    with pytest.raises(CaptureFormatError, match=pattern):
        read_thuman4_calibration(path)
