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
