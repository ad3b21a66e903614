"""EasyMocap intri/extri: metres + OpenCV pixel centres pinned against cv2.projectPoints; every malformed file named."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from capture_cameras import POINTS_MM, rig
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.formats.easymocap import (EasyMocapSmpl, camera_to_easymocap, easymocap_to_camera, read_easymocap_cameras,
                                   read_easymocap_smpl, write_easymocap_cameras, write_easymocap_smpl)

K_CV = np.array([[1100.0, 0, 511.3], [0, 1090.0, 383.9], [0, 0, 1]])
RVEC = np.array([[0.1], [-2.3], [0.05]])
T_M = np.array([[0.2], [0.9], [3.4]])


def _write(folder, intri_extra="", extri_extra="", K=K_CV, rvec=RVEC, T=T_M, rot=True):
    """intri/extri written by hand in EasyMocap's own layout (camera_utils.FileStorage.write)."""
    def mat(key, m):
        m = np.asarray(m, float).reshape(m.shape[0], -1)
        return f"{key}: !!opencv-matrix\n  rows: {m.shape[0]}\n  cols: {m.shape[1]}\n  dt: d\n  data: [{', '.join(map(repr, m.ravel().tolist()))}]\n"
    head = '%YAML:1.0\r\n---\r\nnames:\r\n  - "1"\r\n'
    (folder / "intri.yml").write_text(head + mat("K_1", K) + mat("dist_1", np.zeros((1, 5))) + "H_1: 768\nW_1: 1024\n" + intri_extra)
    ext = mat("R_1", rvec) + (mat("Rot_1", cv2.Rodrigues(rvec)[0]) if rot else "") + mat("T_1", T)
    (folder / "extri.yml").write_text(head + ext + extri_extra)


def test_projection_matches_opencv(tmp_path):
    _write(tmp_path)
    cam = easymocap_to_camera(read_easymocap_cameras(tmp_path / "intri.yml")[0])
    ours, _ = cam.project(POINTS_MM)
    theirs = cv2.projectPoints(POINTS_MM / 1000.0, RVEC, T_M, K_CV, np.zeros(5))[0].reshape(-1, 2)  # metres, OpenCV
    assert np.abs((ours - 0.5) - theirs).max() < 1e-6  # c_opencv = c_deliffas - 0.5
    assert (cam.width, cam.height) == (1024, 768)


def test_write_read_and_numeric_names(tmp_path):
    cams = [camera_to_easymocap(c) for c in rig("full")]
    write_easymocap_cameras(tmp_path, cams)
    back = read_easymocap_cameras(tmp_path)
    for a, b in zip(cams, back):
        assert np.array_equal(a.K, b.K) and np.array_equal(a.T, b.T) and np.array_equal(a.dist, b.dist)
        assert np.abs(a.R - b.R).max() < 1e-14
    _write(tmp_path)  # EasyMocap may store a numeric name unquoted
    (tmp_path / "intri.yml").write_text((tmp_path / "intri.yml").read_text().replace('- "1"', "- 1"))
    assert read_easymocap_cameras(tmp_path)[0].name == "1"


def test_size_required_without_w_h(tmp_path):
    _write(tmp_path)
    (tmp_path / "intri.yml").write_text((tmp_path / "intri.yml").read_text().replace("H_1: 768\nW_1: 1024\n", ""))
    cam = read_easymocap_cameras(tmp_path)[0]
    with pytest.raises(ValueError, match="pass --size WxH"):
        easymocap_to_camera(cam)
    assert easymocap_to_camera(cam, size=(1024, 768)).width == 1024


def test_smpl_json(tmp_path):
    p = EasyMocapSmpl(3, np.array([[0.1, 0.2, 0.3]]), np.array([[0.0, 1.0, 2.0]]), np.zeros((1, 72)), np.ones((1, 10)))
    write_easymocap_smpl(tmp_path / "000001.json", [p])
    (back,) = read_easymocap_smpl(tmp_path / "000001.json")
    assert back.id == 3 and np.array_equal(back.Th, p.Th) and back.poses.shape == (1, 72) and back.expression is None
    (tmp_path / "bad.json").write_text('[{"id": 0, "Rh": [[0, 0, 0]], "Th": [[0, 0]], "poses": [[0]], "shapes": [[0]]}]')
    with pytest.raises(CaptureFormatError, match=r"bad\.json: \[0\]\.Th: expected shape \(1, 3\)"):
        read_easymocap_smpl(tmp_path / "bad.json")
    (tmp_path / "cut.json").write_text('{"annots": [{"id": 0, "Rh": [[0, 0')
    with pytest.raises(CaptureFormatError, match=r"cut\.json: JSON line 1"):
        read_easymocap_smpl(tmp_path / "cut.json")
    (tmp_path / "miss.json").write_text('[{"id": 0, "Rh": [[0, 0, 0]], "Th": [[0, 0, 0]], "shapes": [[0]]}]')
    with pytest.raises(CaptureFormatError, match=r"miss\.json: \[0\]\.poses: missing"):
        read_easymocap_smpl(tmp_path / "miss.json")


@pytest.mark.parametrize("case,pattern", [
    ("missing K", r"intri\.yml: K_1: expected an !!opencv-matrix of shape \(3, 3\), got no such key"),
    ("missing T", r"extri\.yml: T_1: expected .* no such key"),
    ("wrong shape", r"intri\.yml: K_1: expected shape \(3, 3\), got \(2, 3\)"),
    ("nan", r"extri\.yml: T_1: expected finite numbers, got 1 NaN/inf"),
    ("non-rotation", r"extri\.yml: Rot_1: expected a rotation .* det R = -1"),
    ("disagree", r"extri\.yml: Rot_1: expected Rodrigues\(R_1\) within"),
    ("truncated", r"intri\.yml: YAML: expected an OpenCV FileStorage file; YAML: .*"),
    ("empty", r"intri\.yml: YAML: expected an OpenCV FileStorage file, got an empty file"),
    ("no names", r"extri\.yml: names: expected every camera of intri\.yml, missing \['1'\]"),
])
def test_malformed(tmp_path, case, pattern):
    _write(tmp_path)
    intri, extri = tmp_path / "intri.yml", tmp_path / "extri.yml"
    if case == "missing K":
        intri.write_text(intri.read_text().replace("K_1:", "Kx_1:"))
    elif case == "missing T":
        extri.write_text(extri.read_text().replace("T_1:", "Tx_1:"))
    elif case == "wrong shape":
        _write(tmp_path, K=K_CV[:2])
    elif case == "nan":
        _write(tmp_path, T=np.array([[0.2], [np.nan], [3.4]]))
        extri.write_text(extri.read_text().replace("nan", ".nan"))
    elif case == "non-rotation":
        _write(tmp_path, rot=False)
        mirror = -cv2.Rodrigues(RVEC)[0]
        extri.write_text(extri.read_text().replace("R_1:", "Unused_1:") + "Rot_1: !!opencv-matrix\n  rows: 3\n  cols: 3\n"
                         f"  dt: d\n  data: [{', '.join(map(repr, mirror.ravel().tolist()))}]\n")
    elif case == "disagree":
        _write(tmp_path, extri_extra="")
        extri.write_text(extri.read_text().replace("Rot_1", "Old_1").replace("T_1:", "Rot_1: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [1., 0., 0., 0., 1., 0., 0., 0., 1.]\nT_1:"))
    elif case == "truncated":
        text = intri.read_text()
        intri.write_text(text[: text.index("data:") + 20])
    elif case == "empty":
        intri.write_text("")
    elif case == "no names":
        extri.write_text(extri.read_text().replace('- "1"', '- "2"'))
    with pytest.raises(CaptureFormatError, match=pattern):
        read_easymocap_cameras(intri)


def test_files_written_by_opencv_read_back(tmp_path):
    """EasyMocap writes with cv2.FileStorage; deliffas parses the YAML itself (OpenCV's parser hangs on some
    damaged files), so a file OpenCV wrote must read back bit-exact: wrapped data lines, "0.", "1e-05"."""
    K = np.array([[1151.0286864154, 0.0, 509.19], [0.0, 1150.5, 383.25], [0.0, 0.0, 1.0]])
    dist = np.array([[-0.16, 1e-05, 0.0, -2.5e-7, 3.0]])
    R = cv2.Rodrigues(RVEC)[0]
    for name, pairs in (("intri.yml", (("K_01", K), ("dist_01", dist))),
                        ("extri.yml", (("R_01", RVEC), ("Rot_01", R), ("T_01", T_M)))):
        fs = cv2.FileStorage(str(tmp_path / name), cv2.FILE_STORAGE_WRITE)
        fs.write("names", ["01"])
        for key, m in pairs:
            fs.write(key, m)
        if name == "intri.yml":
            fs.write("H_01", 768)
            fs.write("W_01", 1024)
        fs.release()
    (cam,) = read_easymocap_cameras(tmp_path)
    assert cam.name == "01" and (cam.width, cam.height) == (1024, 768)
    np.testing.assert_array_equal(cam.K, K)
    np.testing.assert_array_equal(cam.dist, dist.ravel())
    np.testing.assert_array_equal(cam.T, T_M.ravel())
    np.testing.assert_allclose(cam.R, R, atol=1e-12)
