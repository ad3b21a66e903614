"""Pinhole cameras of a DynaCap rig: projection, rescaling and per-pixel rays.

Conventions (dynacap-formats.md 1.9): world is y-up, millimetres; ``world_to_cam`` is the
row-major 4x4 extrinsic of ``cameras.calibration`` (x_cam = R X + t); the camera looks along +z,
image x to the right, y down. Intrinsics put integer coordinates on pixel *corners*: pixel
(col, row) is sampled at the continuous point (col + 0.5, row + 0.5), as the original rasterizer
does. ``pixel_centers`` and ``Camera.rays`` use that convention; everything in deliffas that
casts rays goes through them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
from jaxtyping import Float, Real

from deliffas.checks import check_finite, check_shape

__all__ = ["Camera", "pixel_centers", "look_at", "ROTATION_TOLERANCE"]

ROTATION_TOLERANCE = 1e-4
"""How far a camera's R may be from a rotation (max |R R^T - I| and |det R - 1|): calibration files
print ~10 significant digits; a scaled or mirrored R is an error, not rounding."""


def pixel_centers(width: int, height: int) -> Float[np.ndarray, "H W 2"]:
    """Continuous image coordinates of every pixel centre.

    Returns:
        (H, W, 2) float64, ``[..., 0]`` = col + 0.5, ``[..., 1]`` = row + 0.5.
    """
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([cols, rows], axis=-1)


def look_at(eye: Real[np.ndarray, "3"] | Sequence[float], target: Real[np.ndarray, "3"] | Sequence[float],
            up: Real[np.ndarray, "3"] | Sequence[float] = (0.0, 1.0, 0.0)) -> Float[np.ndarray, "4 4"]:
    """The (4, 4) ``world_to_cam`` of a camera at ``eye`` looking at ``target``.

    The camera looks along +z; image y points along world -``up`` (image up = world up) and
    image x completes a right-handed frame (x = y cross z).

    Raises:
        ValueError: ``eye`` equals ``target``, or the viewing direction is parallel to ``up``.
    """
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    norm = np.linalg.norm(z)
    if not norm > 0:
        raise ValueError(f"look_at: eye {eye.tolist()} and target coincide")
    z /= norm
    x = np.cross(-np.asarray(up, np.float64), z)
    if not np.linalg.norm(x) > 1e-9:
        raise ValueError(f"look_at: viewing direction {z.tolist()} is parallel to up {list(up)}")
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = R
    world_to_cam[:3, 3] = -R @ eye
    return world_to_cam


@dataclass(frozen=True)
class Camera:
    """One calibrated pinhole camera. The projection is pinhole (as in DELIFFAS); a capture's lens
    distortion is carried, not applied: ``extra["distortion"]`` holds OpenCV's (k1, k2, p1, p2, k3)
    when the source format has them (``deliffas.io.camera_conventions``), and writers refuse to drop
    it silently.

    Attributes:
        name: the calibration's ``name`` token.
        K: (3, 3) float64 intrinsics in pixels for an image of ``width`` x ``height``, integer
            coordinates on pixel corners (pixel (col, row) is sampled at (col + 0.5, row + 0.5)).
        world_to_cam: (4, 4) float64 rigid transform, world mm -> camera mm (x_cam = R X + t; the
            camera looks along +z, image x right, y down).
        width: image width in pixels.
        height: image height in pixels.
        sensor: sensor size (w, h) in mm as the file states it, or None.
        radial: the single radial coefficient of a DynaCap file (unused by the projection).
        extra: format-specific values (e.g. ``distortion``: OpenCV's (k1, k2, p1, p2, k3)), not
            compared by ``==``.
    """

    name: str
    K: Real[np.ndarray, "3 3"]
    world_to_cam: Real[np.ndarray, "4 4"]
    width: int
    height: int
    sensor: tuple[float, float] | None = None
    radial: float = 0.0
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        check_shape(f"camera {self.name} K", self.K, "3 3")
        check_shape(f"camera {self.name} world_to_cam", self.world_to_cam, "4 4")
        check_finite(f"camera {self.name} K", self.K)  # NaN rays would silently hit nothing
        check_finite(f"camera {self.name} world_to_cam", self.world_to_cam)
        if abs(float(np.linalg.det(np.asarray(self.K, np.float64)))) < 1e-12:
            raise ValueError(f"camera {self.name} K: singular intrinsics (fx, fy must be non-zero, last row 0 0 1)")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name}: image size must be positive, got {self.width}x{self.height}")
        R = np.asarray(self.world_to_cam, np.float64)[:3, :3]
        with np.errstate(over="ignore", invalid="ignore"):  # a huge R overflows: NaN/inf fail the test below
            orth = float(np.abs(R @ R.T - np.eye(3)).max())
            det = float(np.linalg.det(R))
        if not (orth <= ROTATION_TOLERANCE and abs(det - 1) <= ROTATION_TOLERANCE):
            # a scaled or mirrored R projects differently in every other format (COLMAP stores a quaternion)
            raise ValueError(f"camera {self.name} world_to_cam: R must be a rotation (R R^T = I, det +1 within "
                             f"{ROTATION_TOLERANCE}); got |R R^T - I| = {orth:.2g}, det = {det:.6g}")

    @property
    def R(self) -> Float[np.ndarray, "3 3"]:
        """(3, 3) world -> camera rotation."""
        return self.world_to_cam[:3, :3]

    @property
    def t(self) -> Float[np.ndarray, "3"]:
        """(3,) world -> camera translation, mm."""
        return self.world_to_cam[:3, 3]

    @property
    def center(self) -> Float[np.ndarray, "3"]:
        """(3,) camera centre in world mm (= -R^T t)."""
        return -self.R.T @ self.t

    @property
    def cam_to_world(self) -> Float[np.ndarray, "4 4"]:
        """(4, 4) inverse of ``world_to_cam``."""
        out = np.eye(4)
        out[:3, :3] = self.R.T
        out[:3, 3] = self.center
        return out

    def project(self, points: Real[np.ndarray, "N 3"]) -> tuple[Float[np.ndarray, "N 2"], Float[np.ndarray, "N"]]:
        """Project world points to continuous image coordinates.

        Args:
            points: (N, 3) world mm.

        Returns:
            pixels (N, 2) float64 (col, row) in the corner convention, depth (N,) camera z in mm.
        """
        check_shape("points", points, "N 3")
        cam = points @ self.R.T + self.t  # (N, 3)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = cam @ self.K.T
            pix = uvw[:, :2] / uvw[:, 2:3]
        return pix, z

    def rescaled(self, width: int, height: int) -> "Camera":
        """The same camera for an image of ``width`` x ``height`` (fx, cx scale with width; fy, cy with height)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        return replace(self, K=K, width=int(width), height=int(height))

    def rays(self, pixels: Real[np.ndarray, "N 2"] | None = None) -> tuple[Float[np.ndarray, "N 3"], Float[np.ndarray, "N 3"]]:
        """World-space rays through pixel centres.

        Args:
            pixels: (N, 2) continuous (col, row) image coordinates; default: every pixel centre
                in row-major order (N = H * W).

        Returns:
            origins (N, 3) float64 world mm (all the camera centre), directions (N, 3) unit.
        """
        if pixels is None:
            pixels = pixel_centers(self.width, self.height).reshape(-1, 2)
        check_shape("pixels", pixels, "N 2")
        pixels = np.asarray(pixels, np.float64)
        # d_world = R^T K^-1 (col, row, 1), one column at a time: an (N, 3) @ (3, 3) product goes
        # through multi-threaded BLAS, which costs more than the arithmetic and stalls under load
        m = self.R.T @ np.linalg.inv(self.K)  # (3, 3)
        col, row = pixels[:, 0], pixels[:, 1]
        d_world = np.empty((len(pixels), 3))
        for j in range(3):
            np.multiply(col, m[j, 0], out=d_world[:, j])
            d_world[:, j] += row * m[j, 1]
            d_world[:, j] += m[j, 2]
        length = np.sqrt(d_world[:, 0] ** 2 + d_world[:, 1] ** 2 + d_world[:, 2] ** 2)
        d_world /= length[:, None]
        origins = np.empty_like(d_world)
        origins[:] = self.center
        return origins, d_world
