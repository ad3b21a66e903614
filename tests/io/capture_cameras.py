"""Cameras shared by the capture-format tests: a look_at rig with varied intrinsics, and comparisons."""

from __future__ import annotations

import numpy as np

from deliffas.io.camera_conventions import DISTORTION, camera_distortion
from deliffas.io.cameras import Camera, look_at

WIDTH, HEIGHT = 160, 120
"""One image size for every camera: ZJU-MoCap stores none, so reading it takes one size= for all."""

POINTS_MM = np.random.default_rng(7).uniform([-600, 100, -600], [600, 1700, 600], (50, 3))
"""World points (mm, y up) inside every camera's view, for projection oracles."""


def rig(distortion: str = "none") -> list[Camera]:
    """Five cameras 2.5-4 m around the origin: non-square pixels, off-centre principal points, skew-free.

    Args:
        distortion: "none", "radial" (k1, k2, k3 only) or "full" (OpenCV k1, k2, p1, p2, k3).
    """
    cams = []
    for i in range(5):
        a = 2 * np.pi * i / 5 + 0.3
        eye = np.array([3000 * np.cos(a), 900 + 250 * i, 3000 * np.sin(a)]) * (1 + 0.1 * i)
        E = look_at(eye, np.array([10.0 * i, 950.0, -20.0]))
        fx = 150.0 + 17.3 * i
        K = np.array([[fx, 0.0, 80.0 + 3.7 * i - 9.1], [0.0, fx * (1.0 + 0.031 * i), 60.0 - 2.9 * i + 4.4], [0, 0, 1]])
        extra = {}
        if distortion == "full":
            extra[DISTORTION] = np.array([-0.21 + 0.01 * i, 0.043, 1.1e-3, -7e-4 * i, -0.005])
        elif distortion == "radial":
            extra[DISTORTION] = np.array([-0.12 - 0.01 * i, 0.021, 0.0, 0.0, 0.0013 * i])
        cams.append(Camera(f"cam{i}", K, E, WIDTH, HEIGHT, extra=extra))
    return cams


def assert_same_cameras(a: list[Camera], b: list[Camera], rtol: float = 1e-9) -> None:
    """Names, sizes, K, world_to_cam and distortion equal to ``rtol`` (relative to each array's scale)."""
    assert [c.name for c in a] == [c.name for c in b]
    for x, y in zip(a, b):
        assert (x.width, x.height) == (y.width, y.height), x.name
        assert np.abs(x.K - y.K).max() <= rtol * np.abs(x.K).max(), (x.name, x.K, y.K)
        assert np.abs(x.R - y.R).max() <= rtol, x.name
        assert np.abs(x.t - y.t).max() <= rtol * np.abs(x.t).max(), (x.name, x.t, y.t)
        assert np.abs(camera_distortion(x) - camera_distortion(y)).max() <= rtol, x.name
