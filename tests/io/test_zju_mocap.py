"""ZJU-MoCap annots.npy: millimetres + OpenCV pixel centres pinned by hand projection; params records; malformed files named."""

from __future__ import annotations

import numpy as np
import pytest

from capture_cameras import POINTS_MM
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.formats.easymocap import EasyMocapSmpl
from deliffas.io.formats.zju_mocap import (read_zju_annots, read_zju_params, write_zju_params, zju_params_path, zju_to_cameras)

K = np.array([[1120.0, 0, 505.2], [0, 1118.0, 512.7], [0, 0, 1]])
ANGLE = 0.7
R = np.array([[np.cos(ANGLE), 0, -np.sin(ANGLE)], [0, 1, 0], [np.sin(ANGLE), 0, np.cos(ANGLE)]])
T_MM = np.array([[120.0], [-40.0], [3900.0]])


def _save(path, cams=None, ims=None):
    """annots.npy as neuralbody's tools/custom/get_annots.py builds it (T = EasyMocap metres * 1000)."""
    cams = cams or {"K": [K], "D": [np.zeros((5, 1))], "R": [R], "T": [T_MM]}
    np.save(path, {"cams": cams, "ims": ims if ims is not None else [{"ims": ["Camera_B1/000000.jpg"]}]})
    return path


def test_projection_matches_neuralbody_convention(tmp_path):
    (cam,) = zju_to_cameras(read_zju_annots(_save(tmp_path / "annots.npy")), (1024, 1024))
    assert cam.name == "Camera_B1"
    x = (POINTS_MM @ R.T + T_MM.ravel()) @ K.T  # x_cam = R X + T in mm; pixel centres on integers (get_rays)
    theirs = x[:, :2] / x[:, 2:]
    ours, _ = cam.project(POINTS_MM)
    assert np.abs((ours - 0.5) - theirs).max() < 1e-6


def test_params_record(tmp_path):
    p = EasyMocapSmpl(0, np.array([[0.1, -0.2, 0.3]]), np.array([[0.0, 0.9, 2.0]]), np.zeros((1, 72)), np.ones((1, 10)))
    path = zju_params_path(tmp_path, 12)
    assert path == tmp_path / "params" / "12.npy" and zju_params_path(tmp_path, 1, new=True).parent.name == "new_params"
    write_zju_params(path, p)
    back = read_zju_params(path)
    assert np.array_equal(back.Rh, p.Rh) and np.array_equal(back.Th, p.Th) and back.poses.shape == (1, 72)
    np.save(tmp_path / "bad.npy", {"poses": np.zeros((1, 72)), "Rh": np.zeros((1, 3)), "shapes": np.zeros((1, 10))})
    with pytest.raises(CaptureFormatError, match=r"bad\.npy: Th: missing"):
        read_zju_params(tmp_path / "bad.npy")


def test_pickles_build_numpy_only(tmp_path):
    import pickle

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    with open(tmp_path / "annots.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "|O", "fortran_order": False, "shape": ()})
        pickle.dump({"cams": Evil()}, fh)
    with pytest.raises(CaptureFormatError, match=r"annots\.npy: pickle: .*refusing to load 'builtins\.print'"):
        read_zju_annots(tmp_path)


@pytest.mark.parametrize("case,pattern", [
    ("missing T", r"annots\.npy: cams/T: missing"),
    ("count", r"annots\.npy: cams/R: expected 1 entries \(one per camera, as cams/K\), got 2"),
    ("shape", r"annots\.npy: cams/K\[0\]: expected shape \(3, 3\), got \(2, 3\)"),
    ("nan", r"annots\.npy: cams/T\[0\]: expected finite numbers, got 1 NaN/inf"),
    ("non-rotation", r"annots\.npy: cams/R\[0\]: expected a rotation .*max \|R R\^T - I\| = 0\.21"),
    ("ims", r"annots\.npy: ims\[0\]\.ims: expected 1 entries"),
    ("truncated", r"annots\.npy: pickle: expected a complete pickled dict"),
    ("not npy", r"annots\.npy: NPY header: expected a \.npy file"),
])
def test_malformed(tmp_path, case, pattern):
    cams = {"K": [K], "D": [np.zeros((5, 1))], "R": [R], "T": [T_MM]}
    path = tmp_path / "annots.npy"
    if case == "missing T":
        del cams["T"]
    elif case == "count":
        cams["R"] = [R, R]
    elif case == "shape":
        cams["K"] = [K[:2]]
    elif case == "nan":
        cams["T"] = [np.array([[1.0], [np.inf], [2.0]])]
    elif case == "non-rotation":
        cams["R"] = [R * 1.1]
    _save(path, cams, [{"ims": ["a.jpg", "b.jpg"]}] if case == "ims" else None)
    if case == "truncated":
        path.write_bytes(path.read_bytes()[:-40])
    elif case == "not npy":
        path.write_bytes(b"hello")
    with pytest.raises(CaptureFormatError, match=pattern):
        read_zju_annots(path)
