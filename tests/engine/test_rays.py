"""The engine's uv stage: camera_rays shades exactly the pixels a dense full-image cast selects."""

from __future__ import annotations

import numpy as np
import trimesh

from deliffas.io.cameras import Camera, look_at
from deliffas.engine.rays import camera_rays
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import UVRaycaster, uv_inner_or_exit
from deliffas.geometry.shell import offset_shell


def _camera(center, width=40, height=32, focal=45.0) -> Camera:
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    return Camera("c", K, look_at(center, [0.0, 0.0, 0.0]), width, height)


def test_camera_rays_equal_the_dense_selection():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=400.0)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    v[:, 1] *= 1.6  # not a sphere: the window is not square
    outer = offset_shell(v, f, 40.0)
    rc = UVRaycaster(v, f, outer, UVAtlas.from_mesh(v, f, resolution=64))
    for center in ([0, 0, 2500.0], [1800.0, 300.0, 1500.0]):
        cam = _camera(center)
        rays = camera_rays(rc, cam)
        dense = rc.cast(cam)
        uv_in, from_outer = uv_inner_or_exit(dense)
        shaded = dense.outer_hit & np.isfinite(uv_in).all(-1) & np.isfinite(dense.uv_outer).all(-1)
        rows, cols = np.nonzero(shaded)
        assert 50 < rays.num_rays < cam.width * cam.height
        np.testing.assert_array_equal(rays.pixels, rows * cam.width + cols)
        np.testing.assert_array_equal(rays.uv_inner, uv_in[shaded])
        np.testing.assert_array_equal(rays.uv_outer, dense.uv_outer[shaded])
        np.testing.assert_array_equal(rays.inner_from_outer, from_outer[shaded])
        _, dirs = cam.rays()
        np.testing.assert_allclose(rays.viewdir, dirs[rows * cam.width + cols], atol=1e-7)
