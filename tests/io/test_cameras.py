"""Camera construction and per-pixel rays."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.io.cameras import Camera, look_at, pixel_centers


def _cam(eye, target, up=(0.0, 1.0, 0.0)) -> Camera:
    K = np.array([[80.0, 0, 32], [0, 80.0, 24], [0, 0, 1]])
    return Camera("c", K, look_at(eye, target, up), 64, 48)


@pytest.mark.parametrize("eye", [[0, 900, 3000], [-2500, 1500, 400], [10, -3000, 5]])
def test_look_at_frame(eye):
    target = np.array([0.0, 900.0, 0.0])
    cam = _cam(eye, target)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(cam.R), 1.0, atol=1e-12)
    np.testing.assert_allclose(cam.center, eye, atol=1e-9)
    pix, depth = cam.project(np.stack([target, target + [0, 100, 0]]))
    np.testing.assert_allclose(pix[0], [32, 24], atol=1e-9)  # target on the principal point
    np.testing.assert_allclose(depth[0], np.linalg.norm(target - eye), rtol=1e-12)
    assert pix[1, 1] < pix[0, 1], "world up is image up"


def test_look_at_degenerate():
    with pytest.raises(ValueError, match="coincide"):
        look_at([1, 2, 3], [1, 2, 3])
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 0, 0], [0, 10, 0])


def test_rays_go_through_their_pixels():
    cam = _cam([300, 1200, 2500], [0, 900, 0])
    centres = pixel_centers(cam.width, cam.height).reshape(-1, 2)
    origins, dirs = cam.rays()
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(origins, np.broadcast_to(cam.center, origins.shape))
    pix, depth = cam.project(origins + 1000.0 * dirs)
    np.testing.assert_allclose(pix, centres, atol=1e-9)
    assert (depth > 0).all()
    sub = centres[[0, 17, 100]]
    np.testing.assert_array_equal(cam.rays(sub)[1], dirs[[0, 17, 100]])


# ------------------------------------------------------------------ plausibility (check_camera, issue 32)
def _K(fx=80.0, fy=80.0, cx=32.0, cy=24.0, last=(0.0, 0.0, 1.0)):
    return np.array([[fx, 0, cx], [0, fy, cy], list(last)], np.float64)


@pytest.mark.parametrize("K, match", [
    (_K(last=(0, 0, 2)), r"K: expected the last row \(0, 0, 1\), got \(0.0, 0.0, 2.0\)"),
    (_K(last=(0.1, 0, 1)), "last row"),
    (_K(fx=-80.0), "positive focal lengths .* fx = -80"),
    (_K(fy=-80.0), "positive focal lengths .* fy = -80"),
    (_K(fx=0.0), "positive focal lengths"),
    (_K(fx=1e-6, fy=1e-6), "positive focal lengths of at least 0.064"),
    (_K(cx=640.0), r"principal point .* \(cx, cy\) = \(640, 24\)"),
    (_K(cy=-100.0), "principal point"),
    (_K(fx=np.nan), "non-finite"),
])
def test_implausible_intrinsics_are_refused(K, match):
    with pytest.raises(ValueError, match=match):
        Camera("c", K, np.eye(4), 64, 48)


@pytest.mark.parametrize("R, match", [
    (np.diag([1.0, 1.0, -1.0]), "R must be a rotation .* det = -1"),
    (2 * np.eye(3), "R must be a rotation"),
])
def test_non_rotations_are_refused(R, match):
    E = np.eye(4)
    E[:3, :3] = R
    with pytest.raises(ValueError, match=match):
        Camera("c", _K(), E, 64, 48)


def test_world_to_cam_last_row_is_checked():
    E = np.eye(4)
    E[3, 0] = 1.0
    with pytest.raises(ValueError, match=r"world_to_cam: expected the last row \(0, 0, 0, 1\)"):
        Camera("c", _K(), E, 64, 48)


def test_plausible_cameras_pass_including_off_centre_crops():
    Camera("c", _K(cx=-30.0, cy=90.0), np.eye(4), 64, 48)  # a crop moves the principal point off the image
    Camera("c", _K(fx=0.1, fy=0.1), np.eye(4), 64, 48)  # a very wide but real field of view
    Camera("c", _K(), np.eye(4), 64, 48).rescaled(8, 6)


def test_check_camera_names_refuses_duplicates():
    from deliffas.io.cameras import check_camera_names

    check_camera_names(["a", "b", "c"], "calib.json")
    with pytest.raises(ValueError, match="calib.json: camera name 'b' appears 2 times"):
        check_camera_names(["a", "b", "b"], "calib.json")
