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

__all__ = ["Camera", "pixel_centers", "look_at", "check_camera", "check_camera_names", "ROTATION_TOLERANCE",
           "MIN_FOCAL_FRACTION", "PRINCIPAL_POINT_MARGIN"]

ROTATION_TOLERANCE = 1e-4
"""How far a camera's R may be from a rotation (max |R R^T - I| and |det R - 1|): calibration files
print ~10 significant digits; a scaled or mirrored R is an error, not rounding."""
MIN_FOCAL_FRACTION = 1e-3
"""The smallest focal length (fx, fy) a camera may have, as a fraction of its image's larger side (a field
of view just under 180 degrees); a zero or negative focal length mirrors or collapses the image."""
PRINCIPAL_POINT_MARGIN = 1.0
"""How far the principal point may lie outside the image, in image sizes: cx in [-m W, (1 + m) W], cy in
[-m H, (1 + m) H]. Crops move it off-centre; beyond this it is a unit or convention error."""


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


def check_camera(name: str, K: Real[np.ndarray, "3 3"], world_to_cam: Real[np.ndarray, "4 4"], width: int,
                 height: int) -> None:
    """The plausibility check every ``Camera`` passes (so every reader and writer of cameras): what no real
    pinhole camera can be is refused.

    Checked: shapes; finite values; a positive image size; K's last row exactly (0, 0, 1); fx and fy at least
    ``MIN_FOCAL_FRACTION`` of the larger image side (positive: a negative one mirrors the image); a
    non-singular K; the principal point within ``PRINCIPAL_POINT_MARGIN`` image sizes of the image;
    world_to_cam's last row (0, 0, 0, 1); R orthonormal with det +1 within ``ROTATION_TOLERANCE``.

    Raises:
        ValueError: ``camera <name> <key>: expected ..., got ...`` (readers re-raise it naming their file).
    """
    check_shape(f"camera {name} K", K, "3 3")
    check_shape(f"camera {name} world_to_cam", world_to_cam, "4 4")
    check_finite(f"camera {name} K", K)  # NaN rays would silently hit nothing
    check_finite(f"camera {name} world_to_cam", world_to_cam)
    K = np.asarray(K, np.float64)
    if width <= 0 or height <= 0:
        raise ValueError(f"camera {name}: image size must be positive, got {width}x{height}")
    if K[2].tolist() != [0.0, 0.0, 1.0]:
        raise ValueError(f"camera {name} K: expected the last row (0, 0, 1), got {tuple(K[2].tolist())} "
                         "(another last row rescales every pixel coordinate)")
    least = MIN_FOCAL_FRACTION * max(width, height)
    if not (K[0, 0] >= least and K[1, 1] >= least):
        raise ValueError(f"camera {name} K: expected positive focal lengths of at least {least:g} px "
                         f"({MIN_FOCAL_FRACTION:g} of the image's larger side), got fx = {K[0, 0]:g}, fy = {K[1, 1]:g}")
    if abs(float(np.linalg.det(K))) < 1e-12:
        raise ValueError(f"camera {name} K: singular intrinsics (fx, fy must be non-zero, last row 0 0 1)")
    m = PRINCIPAL_POINT_MARGIN
    if not (-m * width <= K[0, 2] <= (1 + m) * width and -m * height <= K[1, 2] <= (1 + m) * height):
        raise ValueError(f"camera {name} K: expected the principal point within {m:g} image size of the "
                         f"{width}x{height} image, got (cx, cy) = ({K[0, 2]:g}, {K[1, 2]:g})")
    E = np.asarray(world_to_cam, np.float64)
    if E[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f"camera {name} world_to_cam: expected the last row (0, 0, 0, 1), got {tuple(E[3].tolist())}")
    R = E[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # a huge R overflows: NaN/inf fail the test below
        orth = float(np.abs(R @ R.T - np.eye(3)).max())
        det = float(np.linalg.det(R))
    if not (orth <= ROTATION_TOLERANCE and abs(det - 1) <= ROTATION_TOLERANCE):
        # a scaled or mirrored R projects differently in every other format (COLMAP stores a quaternion)
        raise ValueError(f"camera {name} world_to_cam: R must be a rotation (R R^T = I, det +1 within "
                         f"{ROTATION_TOLERANCE}); got |R R^T - I| = {orth:.2g}, det = {det:.6g}")


def check_camera_names(names: Sequence[str], where: str = "") -> None:
    """Refuse an empty camera name or one given twice (a second camera of the same name would silently replace
    the first in every lookup by name, and a format writes one file or entry per name).

    Raises:
        ValueError: ``[<where>: ]camera name '<name>' appears N times (expected unique names)``.
    """
    prefix = f"{where}: " if where else ""
    if any(not str(n).strip() for n in names):
        raise ValueError(f"{prefix}an empty camera name (expected a name for every camera)")
    seen: dict[str, int] = {}
    for n in names:
        seen[str(n)] = seen.get(str(n), 0) + 1
    twice = [n for n, k in seen.items() if k > 1]
    if twice:
        raise ValueError(f"{prefix}camera name {twice[0]!r} appears {seen[twice[0]]} times "
                         f"({len(twice)} names repeated; expected unique names)")


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
        check_camera(self.name, self.K, self.world_to_cam, self.width, self.height)

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
