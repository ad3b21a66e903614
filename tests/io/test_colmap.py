"""COLMAP round trips: DynaCap and COLMAP share the pixel-centre convention, so K is copied unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.cli import main as cli_main
from deliffas.io.cameras import Camera
from deliffas.io.formats.colmap import cameras_from_colmap, cameras_to_colmap, opencv_principal_point
from deliffas.io.formats.dynacap.calibration import read_calibration, write_calibration
from deliffas.data.synth import dome_cameras


def _cams():
    cams = dome_cameras(np.array([0.0, 900, 0]), 1000.0, 5, 160, 120, seed=4)
    # a non-square-pixel camera with an off-centre principal point
    K = np.array([[310.5, 0, 77.25], [0, 305.0, 64.75], [0, 0, 1]])
    return cams + [Camera("extra", K, cams[0].world_to_cam, 160, 120)]


@pytest.mark.parametrize("text", [False, True])
def test_round_trip_reprojection(tmp_path, text):
    cams = _cams()
    cameras_to_colmap(cams, tmp_path / "model", text=text)
    names = {p.name for p in (tmp_path / "model").iterdir()}
    ext = ".txt" if text else ".bin"
    assert {f"cameras{ext}", f"images{ext}", f"points3D{ext}"} <= names
    back = cameras_from_colmap(tmp_path / "model")
    pts = np.random.default_rng(0).uniform([-800, 0, -800], [800, 1800, 800], (500, 3))
    assert [c.name for c in back] == [c.name for c in cams]
    for a, b in zip(cams, back):
        pa, _ = a.project(pts)
        pb, _ = b.project(pts)
        assert np.abs(pa - pb).max() <= 1e-6 * np.abs(pa).max()
        assert (a.width, a.height) == (b.width, b.height)


def test_pycolmap_projects_like_camera(tmp_path):
    """pycolmap's own projection of the exported model equals Camera.project: no half-pixel shift."""
    import pycolmap

    cams = _cams()
    cameras_to_colmap(cams, tmp_path / "m")
    rec = pycolmap.Reconstruction(str(tmp_path / "m"))
    pts = np.random.default_rng(1).uniform([-500, 200, -500], [500, 1600, 500], (50, 3))
    for i, cam in enumerate(cams):
        img = rec.images[i + 1]
        ours, _ = cam.project(pts)
        theirs = np.stack([img.project_point(p) for p in pts])
        assert np.allclose(ours, theirs, rtol=1e-9, atol=1e-9)
    default = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 64, 48)
    assert list(default.params[2:]) == [32.0, 24.0]  # COLMAP's image centre = W/2: pixel centres at +0.5
    assert opencv_principal_point(cams[-1]) == (76.75, 64.25)


def test_cli_round_trip(tmp_path):
    cams = _cams()
    write_calibration(tmp_path / "cams.calibration", cams)
    assert cli_main(["cameras", str(tmp_path / "cams.calibration"), "--to-colmap", str(tmp_path / "model")]) == 0
    assert cli_main(["cameras", str(tmp_path / "back.calibration"), "--from-colmap", str(tmp_path / "model")]) == 0
    back = read_calibration(tmp_path / "back.calibration")
    for a, b in zip(cams, back):
        assert np.allclose(a.K, b.K, rtol=1e-12) and np.allclose(a.world_to_cam, b.world_to_cam, atol=1e-9)


def test_skew_is_refused(tmp_path):
    K = np.array([[100.0, 2.0, 32], [0, 100, 24], [0, 0, 1]])
    with pytest.raises(ValueError, match="skew"):
        cameras_to_colmap([Camera("s", K, np.eye(4), 64, 48)], tmp_path)
