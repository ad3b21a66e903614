"""The one place where capture-format camera conventions are converted to and from the deliffas ``Camera``.

deliffas (docs/conventions.md): world in millimetres, ``world_to_cam`` (x_cam = R X + t), camera
looking along +z with image x right and y down, pixel (col, row) sampled at the continuous point
(col + 0.5, row + 0.5) with K. The capture formats differ from it in four independent ways, and each
difference is converted by exactly one name below:

- **units**: formats in metres are scaled by ``MM_PER_M`` (``to_camera``/``from_camera``, ``units="m"``).
- **direction**: formats that store camera-to-world poses invert them with ``invert_rigid``.
- **axes**: OpenGL cameras (x right, y up, looking along -z; nerfstudio) differ from OpenCV/deliffas
  cameras by ``OPENGL_FROM_OPENCV`` = diag(1, -1, -1), applied on the camera side of the pose.
- **pixel centres**: OpenCV puts pixel centres on integer coordinates (``cv2.projectPoints``,
  ``cv2.undistort``, ray generators that use ``np.arange(W)``), so its principal point is half a pixel
  smaller than deliffas': c_opencv = c_deliffas - 0.5 (``pixel_centre="integer"``). Formats whose own
  code samples pixels at +0.5 (COLMAP, nerfstudio, HumanRF/ActorsHQ) copy K unchanged
  (``pixel_centre="half"``). Only cx and cy move; focal lengths and skew do not depend on the origin.

Lens distortion is never dropped silently. It travels in ``Camera.extra[DISTORTION]`` as the OpenCV
5-vector (k1, k2, p1, p2, k3) of normalised camera coordinates (the model of ``cv2.projectPoints``;
the deliffas projection itself is a pinhole). A writer whose format cannot hold some coefficient calls
``require_distortion_fits``, which raises ``LossyConversionError`` unless told to drop them, and then
logs a warning. DynaCap's single ``Camera.radial`` coefficient belongs to another model and is treated
the same way by every other format.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Literal

import numpy as np

from deliffas.io.cameras import Camera

__all__ = [
    "MM_PER_M",
    "OPENGL_FROM_OPENCV",
    "DISTORTION",
    "DISTORTION_NAMES",
    "LossyConversionError",
    "to_camera",
    "from_camera",
    "invert_rigid",
    "camera_distortion",
    "require_distortion_fits",
    "rotvec_to_matrix",
    "matrix_to_rotvec",
]

log = logging.getLogger(__name__)

MM_PER_M = 1000.0
"""Millimetres per metre: metre formats' translations are multiplied by it on reading."""

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""(4, 4) change of camera axes between OpenCV (x right, y down, +z forward) and OpenGL (x right,
y up, -z forward); its own inverse. c2w_opengl = c2w_opencv @ OPENGL_FROM_OPENCV."""

DISTORTION = "distortion"
"""Key of ``Camera.extra`` holding the (5,) float64 OpenCV distortion (k1, k2, p1, p2, k3)."""

DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")
"""Names of the five entries of ``Camera.extra[DISTORTION]``, in order."""

Units = Literal["m", "mm"]
PixelCentre = Literal["integer", "half"]


class LossyConversionError(ValueError):
    """A camera holds something (lens distortion) that the target format cannot store.

    ``drop_option``: how to ask for it to be dropped, named in the message (the Python argument
    ``drop_distortion=True``); :meth:`naming` gives the same error naming another spelling (a CLI's flag).
    """

    def __init__(self, reason: str, drop_option: str | None = None):
        told = f"{reason}; undistort the images first, or pass {drop_option}" if drop_option else reason
        super().__init__(told)
        self.reason = reason
        self.drop_option = drop_option

    def naming(self, drop_option: str) -> "LossyConversionError":
        """This error telling to pass ``drop_option`` (e.g. ``--drop-distortion``); itself where nothing is droppable."""
        return LossyConversionError(self.reason, drop_option) if self.drop_option else self


def invert_rigid(M: np.ndarray) -> np.ndarray:
    """The inverse of a (4, 4) rigid transform [R t; 0 1]: [R^T -R^T t; 0 1] (camera-to-world <-> world-to-camera)."""
    M = np.asarray(M, np.float64)
    out = np.eye(4)
    out[:3, :3] = M[:3, :3].T
    out[:3, 3] = -M[:3, :3].T @ M[:3, 3]
    return out


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of an axis-angle vector (3,) whose norm is the angle in radians (Rodrigues)."""
    from scipy.spatial.transform import Rotation  # scipy is a dependency; imported here to keep `import deliffas.io` light

    return Rotation.from_rotvec(np.asarray(rotvec, np.float64)).as_matrix()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """(3,) axis-angle vector of a (3, 3) rotation (angle in [0, pi])."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, np.float64)).as_rotvec()


def to_camera(name: str, K: np.ndarray, world_to_cam: np.ndarray, width: int, height: int, *,
              units: Units, pixel_centre: PixelCentre, distortion: np.ndarray | None = None) -> Camera:
    """A deliffas ``Camera`` from a format's OpenCV-axes world-to-camera pose.

    Args:
        K: (3, 3) intrinsics in pixels, in the format's pixel-centre convention.
        world_to_cam: (4, 4) world -> camera (OpenCV axes), translation in ``units``.
        units: "m" or "mm", the format's length unit.
        pixel_centre: "integer" (OpenCV: pixel centres on integers) or "half" (deliffas/COLMAP).
        distortion: (5,) OpenCV (k1, k2, p1, p2, k3), or fewer leading entries, or None.
    """
    K = np.array(K, np.float64)
    if pixel_centre == "integer":
        # OpenCV samples pixel (col, row) at (col, row); deliffas at (col + 0.5, row + 0.5): the same
        # ray has a principal point half a pixel further along in deliffas coordinates.
        K[0, 2] += 0.5
        K[1, 2] += 0.5
    E = np.array(world_to_cam, np.float64)
    if units == "m":
        with np.errstate(over="ignore"):  # a translation beyond float64 in mm becomes inf, which Camera refuses
            E[:3, 3] *= MM_PER_M  # deliffas worlds are millimetres; rotations are unit-free
    extra = {}
    if distortion is not None:
        d = np.zeros(5)
        d[: len(np.ravel(distortion))] = np.ravel(distortion)
        extra[DISTORTION] = d
    return Camera(str(name), K, E, int(width), int(height), extra=extra)


def from_camera(camera: Camera, *, units: Units, pixel_centre: PixelCentre) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of ``to_camera``: (K (3, 3) in the format's pixel convention, world_to_cam (4, 4)
    in ``units``, distortion (5,) OpenCV order, zeros when the camera has none)."""
    K = np.array(camera.K, np.float64)
    if pixel_centre == "integer":
        K[0, 2] -= 0.5  # c_opencv = c_deliffas - 0.5 (see to_camera)
        K[1, 2] -= 0.5
    E = np.array(camera.world_to_cam, np.float64)
    if units == "m":
        E[:3, 3] /= MM_PER_M
    return K, E, camera_distortion(camera)


def camera_distortion(camera: Camera) -> np.ndarray:
    """(5,) float64 OpenCV distortion (k1, k2, p1, p2, k3) of ``camera``; zeros when it has none."""
    d = camera.extra.get(DISTORTION)
    out = np.zeros(5)
    if d is not None:
        d = np.ravel(np.asarray(d, np.float64))
        out[: min(5, len(d))] = d[:5]
        if len(d) > 5 and np.any(d[5:] != 0):
            raise LossyConversionError(f"camera {camera.name}: {len(d)} distortion coefficients; deliffas carries "
                                       "the OpenCV five (k1, k2, p1, p2, k3)")
    return out


def require_distortion_fits(camera: Camera, fmt: str, holds: tuple[str, ...], drop: bool = False,
                            radial_fits: bool = False) -> Camera:
    """Check that ``fmt`` can store ``camera``'s lens distortion; return the camera it will store.

    Args:
        holds: names from ``DISTORTION_NAMES`` the format stores (``()`` for none).
        drop: instead of raising, zero what the format cannot hold and log a warning.
        radial_fits: the format stores DynaCap's ``Camera.radial`` (only DynaCap itself).

    Raises:
        LossyConversionError: a non-zero coefficient the format has no place for (and not ``drop``).
    """
    d = camera_distortion(camera)
    lost = [f"{n}={v:g}" for n, v in zip(DISTORTION_NAMES, d) if v != 0 and n not in holds]
    if camera.radial != 0 and not radial_fits:
        lost.append(f"DynaCap radial={camera.radial:g}")
    if not lost:
        return camera
    message = (f"camera {camera.name}: {fmt} cannot store lens distortion {', '.join(lost)} "
               f"(it holds {', '.join(holds) if holds else 'none'})")
    if not drop:
        raise LossyConversionError(message, "drop_distortion=True")
    log.warning("%s; dropped as asked (drop_distortion=True)", message)
    kept = np.array([v if n in holds else 0.0 for n, v in zip(DISTORTION_NAMES, d)])
    extra = dict(camera.extra)
    extra[DISTORTION] = kept
    return replace(camera, radial=camera.radial if radial_fits else 0.0, extra=extra)
