"""Rasterised uvs of the inner and outer surfaces per camera pixel, with depth peeling (the ray caster's hits).

The paper gets its uv maps from a GPU rasteriser; this module does the same on the CPU and gives
the shaded rays ``geometry.raycast`` gives (``UVRaycaster.cast_foreground`` + ``uv_inner_or_exit``):

* pixel (col, row) is sampled at its centre (col + 0.5, row + 0.5); a triangle covers it when the
  centre lies inside or on the triangle's projection (both orientations: rays meet back faces too);
* per pixel, the inner surface's nearest fragment (its first hit) and the outer surface's three
  nearest fragments are kept (z-buffers on camera depth, which orders hits along one pixel's ray as
  the ray parameter t does, t = z |K^-1 (x, y, 1)|);
* a pixel is shaded when the outer surface covers it and either the inner surface covers it or an
  outer fragment lies more than ``peel_eps`` (along the ray, mm) beyond the first outer one: the
  outer exit, the ray caster's re-cast from ``t1 + eps``;
* barycentrics are perspective-correct (those of the 3-D hit point, as open3d's), the uvs the
  per-corner atlas uvs interpolated with them.

Differences from the ray caster are limited to pixel centres within round-off of a triangle edge
(open3d intersects in float32, this module in float64) and are bounded by a test. A vertex behind
the camera (camera z <= 0) makes the projection meaningless: :meth:`UVRasterizer.shaded_pixels`
then returns None and the caller ray-casts.

Two implementations give the same pixels: a C kernel (``deliffas/csrc/rasterize.c``, built by :mod:`deliffas.native` once per
process) and a vectorised numpy one over (triangle, pixel) pairs, used with ``DELIFFAS_NATIVE=0``,
without a C compiler, or with ``method="numpy"``.
"""

from __future__ import annotations

import ctypes
import dataclasses
import logging
import threading
import weakref
from typing import Literal

import numpy as np
from jaxtyping import Integer, Real

from deliffas.checks import check_shape
from deliffas.geometry.arrays import ArrayLike, to_numpy
from deliffas.geometry.camera_rays import CameraRays, camera_rays
from deliffas.geometry.shaded_pixels import ShadedPixels
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import PEEL_EPS_REL, UVRaycaster, projected_pixel_window
from deliffas.io.cameras import Camera
from deliffas.native import LazyLibrary, header_structs

__all__ = ["ShadedPixels", "UVRasterizer", "OUTER_LAYERS", "raster_kernel_available", "frame_rasterizer",
           "rasterized_camera_rays"]

logger = logging.getLogger(__name__)

OUTER_LAYERS = 3
"""Outer fragments kept per pixel: the first hit and two more, of which the first farther than
``peel_eps`` is the exit (two fragments at one depth occur where a pixel centre lies on an edge)."""

_SLACK = 7  # z-buffer elements after the last layer: the kernel reads and writes 8 pixels at a time
_PAIR_CHUNK = 1 << 22  # (triangle, pixel) pairs per chunk of the numpy implementation

Method = Literal["auto", "native", "numpy"]


# signatures and deliffas_raster_uv_args: rasterize.h
_KERNEL = LazyLibrary("rasterize", "rasterize.c", ("-fno-fast-math", "-ffp-contract=off", "-fno-math-errno"),
                      fallback="the numpy rasteriser, much slower")


def raster_kernel_available() -> bool:
    """Whether the C rasteriser is built and loaded in this process (builds it on the first call)."""
    return _KERNEL.get() is not None


def _project(camera: Camera, verts: np.ndarray) -> np.ndarray:
    """(V, 3) float64 (x px, y px, camera z mm) of world points (V, 3) mm."""
    cam = verts @ camera.R.T + camera.t  # (V, 3) camera frame
    img = cam @ np.asarray(camera.K, np.float64).T
    out = np.empty_like(cam)
    out[:, 0] = img[:, 0] / img[:, 2]
    out[:, 1] = img[:, 1] / img[:, 2]
    out[:, 2] = cam[:, 2]
    return out


class UVRasterizer:
    """One frame's inner and outer surfaces, rasterised per camera (scratch buffers reused across calls, one set per
    thread).

    numpy inside: vertices and faces may be numpy arrays or torch tensors (copied to numpy here, the
    one conversion); the results (:class:`ShadedPixels`) are numpy.

    Args:
        inner_verts: (V, 3) float, mm, the posed mesh.
        faces: (F, 3) int, shared by both surfaces.
        outer_verts: (V, 3) float, mm, the offset shell.
        atlas: UVAtlas with ``face_uvs`` (F, 3).
        method: "auto" (the C kernel when available, else numpy), "native" or "numpy".
    """

    def __init__(self, inner_verts: Real[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"],
                 outer_verts: Real[ArrayLike, "V 3"], atlas: UVAtlas, method: Method = "auto") -> None:
        sizes = check_shape("inner_verts", inner_verts, "V 3")
        sizes = check_shape("faces", faces, "F 3", sizes)
        check_shape("outer_verts", outer_verts, "V 3", sizes)
        if atlas.num_faces != sizes["F"]:
            raise ValueError(f"atlas: face_uvs has {atlas.num_faces} rows, faces has {sizes['F']}")
        if method not in ("auto", "native", "numpy"):
            raise ValueError(f"method: expected 'auto', 'native' or 'numpy', got {method!r}")
        self.method = method
        self.inner = to_numpy(inner_verts, np.float64)  # the numpy boundary: tensors (any device) come to the CPU
        self.outer = to_numpy(outer_verts, np.float64)
        self.faces = np.ascontiguousarray(to_numpy(faces), np.int32)
        self.corner_uvs = np.ascontiguousarray(atlas.uvs.astype(np.float32)[atlas.face_uvs].reshape(-1, 6))  # (F, 6)
        diag = float(np.linalg.norm(self.outer.max(0) - self.outer.min(0))) if len(self.outer) else 1.0
        self.peel_eps = PEEL_EPS_REL * max(diag, 1e-6)
        self.hull_points = np.concatenate([self.inner, self.outer])  # (2V, 3)
        self._local = threading.local()  # scratch buffers per thread: frames may render in several at once

    def _buffer(self, name: str, size: int, dtype) -> np.ndarray:
        scratch = self._local.__dict__.setdefault("scratch", {})
        buf = scratch.get(name)
        if buf is None or buf.size < size:
            buf = scratch[name] = np.empty(max(size, 1), dtype)
        return buf[:size]

    def depth_pass(self, camera: Camera) -> Integer[np.ndarray, "h w"] | None:
        """Face index (h, w) int32 (-1 = none) of the outer surface's nearest fragment per pixel of the
        projected window: one plain z-buffer pass, no peeling and no uvs (C kernel only; the benchmarks'
        baseline). None when a vertex is behind the camera."""
        window = projected_pixel_window(camera, self.hull_points)
        lib = _KERNEL.get()
        if window is None or lib is None:
            return None
        c0, r0, c1, r1 = window
        pout = _project(camera, self.outer)
        n = (c1 - c0) * (r1 - r0)
        z, face = self._buffer("zi", n + _SLACK, np.float32), self._buffer("fi", n + _SLACK, np.int32)
        if lib.deliffas_raster_depth(pout.ctypes.data, self.faces.ctypes.data, len(self.faces), c0, r0,
                                     c1 - c0, r1 - r0, z.ctypes.data, face.ctypes.data) != 0:
            raise MemoryError("UVRasterizer.depth_pass: the face bins could not be allocated")
        return face[:n].reshape(r1 - r0, c1 - c0)

    def shaded_pixels(self, camera: Camera, viewdir: bool = True) -> ShadedPixels | None:
        """The shaded pixels of ``camera``, or None when a vertex is not in front of it (ray-cast then).
        ``viewdir=False`` leaves out the view directions (most variants read none)."""
        window = projected_pixel_window(camera, self.hull_points)
        if window is None:
            return None
        c0, r0, c1, r1 = window
        pin, pout = _project(camera, self.inner), _project(camera, self.outer)
        m = np.ascontiguousarray(camera.R.T @ np.linalg.inv(camera.K), np.float64)  # (3, 3): pixel -> world dir
        lib = None if self.method == "numpy" else _KERNEL.get()
        if lib is None and self.method == "native":
            raise RuntimeError(f"UVRasterizer: the C rasteriser is unavailable ({_KERNEL.load().reason})")
        if lib is None:
            got = _raster_numpy(pin, pout, self.faces, self.corner_uvs, (c0, r0, c1, r1), camera.width, m,
                                self.peel_eps)
            return got if viewdir else dataclasses.replace(got, viewdir=None)
        w, h = c1 - c0, r1 - r0
        n = w * h
        ptr = lambda a: a.ctypes.data  # noqa: E731
        zi, fi = self._buffer("zi", n + _SLACK, np.float32), self._buffer("fi", n + _SLACK, np.int32)
        zo, fo = (self._buffer("zo", n * OUTER_LAYERS + _SLACK, np.float32),
                  self._buffer("fo", n * OUTER_LAYERS + _SLACK, np.int32))
        pix, uv_in = self._buffer("pix", n, np.int64), self._buffer("uv_in", 2 * n, np.float32)
        from_outer, uv_out = self._buffer("from_outer", n, np.uint8), self._buffer("uv_out", 2 * n, np.float32)
        dirs = self._buffer("viewdir", 3 * n, np.float32) if viewdir else None
        args = header_structs(_KERNEL.header)["deliffas_raster_uv_args"](
            pin=ptr(pin), pout=ptr(pout), faces=ptr(self.faces), F=len(self.faces), corner_uvs=ptr(self.corner_uvs),
            c0=c0, r0=r0, w=w, h=h, W=camera.width, m=ptr(m), eps=self.peel_eps, zi=ptr(zi), fi=ptr(fi), zo=ptr(zo),
            fo=ptr(fo), pix=ptr(pix), uv_in=ptr(uv_in), from_outer=ptr(from_outer), uv_out=ptr(uv_out),
            viewdir=ptr(dirs) if dirs is not None else None)
        count = lib.deliffas_raster_uv(ctypes.byref(args))
        if count < 0:
            raise MemoryError("UVRasterizer.shaded_pixels: the face bins could not be allocated")
        return ShadedPixels(pixels=pix[:count].copy(), uv_inner=uv_in[: 2 * count].reshape(count, 2).copy(),
                            inner_from_outer=from_outer[:count].astype(bool),
                            uv_outer=uv_out[: 2 * count].reshape(count, 2).copy(),
                            viewdir=dirs[: 3 * count].reshape(count, 3).copy() if dirs is not None else None)


# one rasteriser per frame geometry (its ray caster), alive as long as the ray caster
_RASTERIZERS: "weakref.WeakKeyDictionary[UVRaycaster, UVRasterizer]" = weakref.WeakKeyDictionary()


def frame_rasterizer(raycaster: UVRaycaster) -> UVRasterizer:
    """The rasteriser of the surfaces of ``raycaster`` (built once per ray caster)."""
    rz = _RASTERIZERS.get(raycaster)
    if rz is None:
        rz = _RASTERIZERS[raycaster] = UVRasterizer(raycaster.inner_verts, raycaster.faces, raycaster.outer_verts,
                                                    raycaster.atlas)
    return rz


def rasterized_camera_rays(raycaster: UVRaycaster, camera: Camera, viewdir: bool = True) -> CameraRays:
    """``camera_rays(raycaster, camera)`` by rasterisation (numpy; the ray caster where a vertex is behind the
    camera); ``viewdir=False``: the rasteriser leaves the view directions out (``viewdir`` None)."""
    got = frame_rasterizer(raycaster).shaded_pixels(camera, viewdir)
    if got is None:
        return camera_rays(raycaster, camera)
    return CameraRays.from_shaded(got, camera)


# ------------------------------------------------------------------------------------------- numpy version
def _fragments(P: np.ndarray, faces: np.ndarray, window: tuple[int, int, int, int]):
    """Every (pixel, depth, face) fragment of a surface in the window: flat window pixel (M,) int64,
    1 / z (M,) float32 (rounded as the kernel stores it), face (M,) int64."""
    c0, r0, c1, r1 = window
    w = c1 - c0
    a, b, c = P[faces[:, 0]], P[faces[:, 1]], P[faces[:, 2]]  # (F, 3) each
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    xs, ys = np.stack([a[:, 0], b[:, 0], c[:, 0]]), np.stack([a[:, 1], b[:, 1], c[:, 1]])
    with np.errstate(invalid="ignore"):
        cs = np.maximum(np.ceil(xs.min(0) - 0.5), c0)
        ce = np.minimum(np.floor(xs.max(0) - 0.5), c1 - 1)
        rs = np.maximum(np.ceil(ys.min(0) - 0.5), r0)
        re = np.minimum(np.floor(ys.max(0) - 0.5), r1 - 1)
        ok = (area != 0) & np.isfinite(area) & (ce >= cs) & (re >= rs)
    tri = np.flatnonzero(ok)
    nc, nr = (ce[tri] - cs[tri] + 1).astype(np.int64), (re[tri] - rs[tri] + 1).astype(np.int64)
    counts = nc * nr
    parts = []
    cum = np.cumsum(counts)
    edges = np.searchsorted(cum, np.arange(_PAIR_CHUNK, int(cum[-1]) if len(cum) else 0, _PAIR_CHUNK), side="right")
    for start, stop in zip([0, *edges], [*edges, len(tri)]):
        if stop <= start:
            continue
        sel = slice(start, stop)
        t = np.repeat(tri[sel], counts[sel])  # (M,) triangle of each pair
        offset = np.arange(len(t)) - np.repeat(np.cumsum(counts[sel]) - counts[sel], counts[sel])
        ncol = np.repeat(nc[sel], counts[sel])
        col = np.repeat(cs[tri[sel]].astype(np.int64), counts[sel]) + offset % ncol
        row = np.repeat(rs[tri[sel]].astype(np.int64), counts[sel]) + offset // ncol
        x, y = col + 0.5, row + 0.5
        A, B, C = a[t], b[t], c[t]
        inv = 1.0 / area[t]
        with np.errstate(over="ignore", invalid="ignore"):  # faces projected absurdly far: no pixel, as the kernel
            l0 = ((C[:, 0] - B[:, 0]) * (y - B[:, 1]) - (C[:, 1] - B[:, 1]) * (x - B[:, 0])) * inv
            l1 = ((A[:, 0] - C[:, 0]) * (y - C[:, 1]) - (A[:, 1] - C[:, 1]) * (x - C[:, 0])) * inv
            l2 = ((B[:, 0] - A[:, 0]) * (y - A[:, 1]) - (B[:, 1] - A[:, 1]) * (x - A[:, 0])) * inv
            # 1 / z interpolated and rounded as the kernel stores it; the kernel drops a covered centre whose
            # rounded value is not > 0 (none with every vertex in front of the camera)
            inv_z = (l0 * (1.0 / A[:, 2]) + l1 * (1.0 / B[:, 2]) + l2 * (1.0 / C[:, 2])).astype(np.float32)
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0) & (inv_z > 0)
        parts.append((((row - r0) * w + (col - c0))[inside], inv_z[inside], t[inside]))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.int64)
    return tuple(np.concatenate(p) for p in zip(*parts))


def _face_uv(P, faces, corner_uvs, face, x, y) -> np.ndarray:
    """(M, 2) float32 perspective-correct uvs of faces (M,) at pixel centres (x, y) (M,)."""
    A, B, C = P[faces[face, 0]], P[faces[face, 1]], P[faces[face, 2]]
    inv = 1.0 / ((B[:, 0] - A[:, 0]) * (C[:, 1] - A[:, 1]) - (B[:, 1] - A[:, 1]) * (C[:, 0] - A[:, 0]))
    q0 = ((C[:, 0] - B[:, 0]) * (y - B[:, 1]) - (C[:, 1] - B[:, 1]) * (x - B[:, 0])) * inv * (1.0 / A[:, 2])
    q1 = ((A[:, 0] - C[:, 0]) * (y - C[:, 1]) - (A[:, 1] - C[:, 1]) * (x - C[:, 0])) * inv * (1.0 / B[:, 2])
    q2 = ((B[:, 0] - A[:, 0]) * (y - A[:, 1]) - (B[:, 1] - A[:, 1]) * (x - A[:, 0])) * inv * (1.0 / C[:, 2])
    s = 1.0 / (q0 + q1 + q2)
    cu = corner_uvs[face].astype(np.float64)  # (M, 6)
    return np.stack([(q0 * cu[:, 0] + q1 * cu[:, 2] + q2 * cu[:, 4]) * s,
                     (q0 * cu[:, 1] + q1 * cu[:, 3] + q2 * cu[:, 5]) * s], axis=1).astype(np.float32)


def _raster_numpy(pin, pout, faces, corner_uvs, window, width: int, m: np.ndarray, eps: float) -> ShadedPixels:
    """The kernel's result from sorted fragments (the reference the C kernel is tested against)."""
    c0, r0, c1, r1 = window
    w = c1 - c0
    n = w * (r1 - r0)
    faces64 = faces.astype(np.int64)
    inner_face = np.full(n, -1, np.int64)
    pix, inv_z, face = _fragments(pin, faces64, window)
    order = np.lexsort((-inv_z, pix))  # nearest first per pixel
    pix, face = pix[order], face[order]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    inner_face[pix[first]] = face[first]
    pix, inv_z, face = _fragments(pout, faces64, window)
    order = np.lexsort((-inv_z, pix))
    pix, face = pix[order], face[order]
    z = 1.0 / inv_z[order].astype(np.float64)
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    rank = np.arange(len(pix)) - np.maximum.accumulate(np.where(first, np.arange(len(pix)), 0))
    outer_face = np.full(n, -1, np.int64)
    outer_face[pix[first]] = face[first]
    # window pixel centres and ray lengths |R^T K^-1 (x, y, 1)|
    col, row = pix % w + c0 + 0.5, pix // w + r0 + 0.5
    length = np.sqrt(sum((m[j, 0] * col + m[j, 1] * row + m[j, 2]) ** 2 for j in range(3)))
    z0 = np.repeat(z[first], np.diff(np.append(np.flatnonzero(first), len(pix))))
    later = (rank > 0) & (rank < OUTER_LAYERS) & (z > z0 + eps / length)
    later_idx = np.flatnonzero(later)
    keep = np.ones(len(later_idx), bool)
    keep[1:] = pix[later_idx[1:]] != pix[later_idx[:-1]]
    exit_face = np.full(n, -1, np.int64)
    exit_face[pix[later_idx[keep]]] = face[later_idx[keep]]
    from_outer = (inner_face < 0) & (exit_face >= 0)
    shaded = np.flatnonzero((outer_face >= 0) & ((inner_face >= 0) | from_outer))  # row-major window order
    x, y = shaded % w + c0 + 0.5, shaded // w + r0 + 0.5
    fo = from_outer[shaded]
    uv_in = np.empty((len(shaded), 2), np.float32)
    uv_in[~fo] = _face_uv(pin, faces64, corner_uvs, inner_face[shaded[~fo]], x[~fo], y[~fo])
    uv_in[fo] = _face_uv(pout, faces64, corner_uvs, exit_face[shaded[fo]], x[fo], y[fo])
    dirs = np.stack([m[j, 0] * x + m[j, 1] * y + m[j, 2] for j in range(3)], axis=1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return ShadedPixels(pixels=(shaded // w + r0) * width + shaded % w + c0, uv_inner=uv_in, inner_from_outer=fo,
                        uv_outer=_face_uv(pout, faces64, corner_uvs, outer_face[shaded], x, y),
                        viewdir=dirs.astype(np.float32))
