"""Screen-space uv of the inner and outer surfaces per camera pixel, with depth peeling.

Each pixel (col, row) casts the ray through its centre (col + 0.5, row + 0.5) from
``Camera.rays`` (docs/conventions.md). The inner surface (the posed mesh) gives its first hit;
the outer surface (the offset shell: same faces and per-corner uvs, moved vertices) gives its
first hit and its second, "exit" hit (depth peeling, dynacap-formats.md 3.4). Where a ray misses
the inner surface, DELIFFAS takes the outer surface's exit hit in its place
(``uv_inner_or_exit``).

Barycentrics: open3d's ``primitive_uvs`` (b1, b2) of a hit on triangle (v0, v1, v2) mean the
point (1 - b1 - b2) v0 + b1 v1 + b2 v2, so ``bary = (1 - b1 - b2, b1, b2)`` (checked by a test).
Per-corner uv at a hit: uv = sum_k bary_k * uvs[face_uvs[face, k]].

open3d is imported at call time, only here (shell.py reaches it through these functions).

Arrays: open3d works on numpy, so this module is numpy inside. ``build_scene`` and ``UVRaycaster``
take numpy arrays or torch tensors (any device; converted once, on entry) and every result
(``RaycastHits``, hit arrays) is numpy.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, fields
from typing import Literal, Sequence

import numpy as np
from jaxtyping import Bool, Float, Integer, Real, Shaped

from deliffas.checks import check_finite, check_shape
from deliffas.optional import import_optional
from deliffas.io.cameras import Camera
from deliffas.geometry.arrays import ArrayLike, to_numpy
from deliffas.geometry.atlas import UVAtlas

__all__ = [
    "RaycastHits",
    "UVRaycaster",
    "uv_inner_or_exit",
    "projected_pixel_window",
    "build_scene",
    "first_hits",
    "all_hits",
    "PEEL_EPS_REL",
]

PEEL_EPS_REL = 1e-5
"""Depth peeling re-casts from ``hit + eps * dir`` with eps = PEEL_EPS_REL x the diagonal of the
outer surface's bounding box (about 0.02 mm for a 2 m person): well above float32 round-off of
the hit point (~3e-4 mm at 3 m) and far below the 0.1 mm depth quantum of the original renderer,
which also merges hits closer than its quantum."""

BOX_PAD_REL = 1e-3
"""Ray culling: a ray is cast only when it meets the bounding box of both surfaces grown by
BOX_PAD_REL x the outer surface's diagonal on every side (about 2 mm for a 2 m person), far
more than the float32 round-off of the box test, so a ray that can hit a triangle is never
culled."""

_BOX_CHUNK = 16384  # rays per chunk of the box test (its temporaries stay in cache)

PeelMethod = Literal["recast", "list"]
ExitRays = Literal["all", "inner_miss"]


def _o3d():
    return import_optional("open3d", "deliffas.geometry.raycast needs the 'open3d' package (and its system "
                                     "libraries, see scripts/system_deps.sh)")


def build_scene(verts: Real[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"]):
    """An open3d ``RaycastingScene`` holding one triangle mesh (float32 positions).

    Args:
        verts: (V, 3) float, mm (finite: NaN or inf raise ValueError).
        faces: (F, 3) int in [0, V).
    """
    sizes = check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    check_finite("verts", verts)  # open3d would silently drop the faces of a NaN vertex
    if len(faces) and (int(np.min(faces)) < 0 or int(np.max(faces)) >= sizes["V"]):
        raise ValueError(f"faces: indices must be in [0, {sizes['V']}), got [{int(np.min(faces))}, {int(np.max(faces))}]")
    verts, faces = to_numpy(verts), to_numpy(faces)
    o3d = _o3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(verts, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
    )
    return scene


def _rays(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N, 6) float32 rays [origin, direction] as open3d wants them."""
    r = np.empty((len(origins), 6), np.float32)
    r[:, :3] = origins
    r[:, 3:] = directions
    return r


def _cast(scene, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hits of (N, 6) float32 rays: t (N,) float32, face (N,) int64, bary (N, 3) float32."""
    o3d = _o3d()
    if len(rays) == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy()
    miss = ~np.isfinite(t)
    face = ans["primitive_ids"].numpy().astype(np.int64)
    face[miss] = -1
    b12 = ans["primitive_uvs"].numpy()
    zero = np.float32(0.0)
    bary = np.empty((len(t), 3), np.float32)
    bary[:, 1] = np.where(miss, zero, b12[:, 0])  # column-wise: 1-D masks are fast, 2-D row masks are not
    bary[:, 2] = np.where(miss, zero, b12[:, 1])
    bary[:, 0] = np.where(miss, zero, 1.0 - b12[:, 0] - b12[:, 1])
    return t, face, bary


def first_hits(scene, origins: Real[np.ndarray, "N 3"], directions: Real[np.ndarray, "N 3"]
               ) -> tuple[Float[np.ndarray, "N"], Integer[np.ndarray, "N"], Float[np.ndarray, "N 3"]]:
    """First intersection of each ray.

    Args:
        scene: from ``build_scene``.
        origins: (N, 3) float, mm.
        directions: (N, 3) float, unit (t is then in mm).

    Returns:
        t (N,) float32 (inf on a miss), face (N,) int64 (-1 on a miss), bary (N, 3) float32
        (0 on a miss).
    """
    check_shape("origins", origins, "N 3")
    check_shape("directions", directions, "N 3", {"N": len(origins)})
    return _cast(scene, _rays(origins, directions))


def all_hits(scene, origins: Real[np.ndarray, "N 3"], directions: Real[np.ndarray, "N 3"]
             ) -> tuple[Integer[np.ndarray, "M"], Float[np.ndarray, "M"], Integer[np.ndarray, "M"], Float[np.ndarray, "M 3"]]:
    """Every intersection of every ray (open3d ``list_intersections``), sorted by (ray, t).

    Returns:
        ray_ids (M,) int64, t (M,) float32, face (M,) int64, bary (M, 3) float32.
    """
    check_shape("origins", origins, "N 3")
    check_shape("directions", directions, "N 3", {"N": len(origins)})
    return _all_hits(scene, _rays(origins, directions))


def _all_hits(scene, rays: np.ndarray):
    o3d = _o3d()
    if len(rays) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    ans = scene.list_intersections(o3d.core.Tensor(rays))
    ray_ids = ans["ray_ids"].numpy().astype(np.int64)
    t = ans["t_hit"].numpy()
    face = ans["primitive_ids"].numpy().astype(np.int64)
    b12 = ans["primitive_uvs"].numpy()
    order = np.lexsort((t, ray_ids))
    bary = np.empty((len(t), 3), np.float32)
    bary[:, 1:] = b12
    bary[:, 0] = 1.0 - b12[:, 0] - b12[:, 1]
    return ray_ids[order], t[order], face[order], bary[order]


@dataclass(frozen=True)
class RaycastHits:
    """Per-ray hits of the inner and outer surfaces for one camera (or a stack of cameras).

    Shapes: ``R`` = (H, W) for a full image, (N,) for a pixel subset, (C, H, W) from
    ``UVRaycaster.cast_batch``. Depths are ray parameters t in mm from the camera centre along
    the unit ray (inf on a miss); faces are -1, barycentrics 0 and uvs NaN on a miss.

    Attributes:
        inner_hit: R bool, the ray meets the inner surface.
        inner_face: R int64.
        inner_bary: R + (3,) float32.
        uv_inner: R + (2,) float32.
        inner_depth: R float32, mm.
        outer_hit: R bool, first hit of the outer surface.
        outer_face, outer_bary, uv_outer, outer_depth: as for the inner surface.
        outer_exit_hit: R bool, a second (peeled) outer hit exists.
        outer_exit_face, outer_exit_bary, uv_outer_exit, outer_exit_depth: of that second hit.
        pixels: (N, 2) int64 (col, row) of the cast pixels for a subset, None for a full image.
    """

    inner_hit: Bool[np.ndarray, "*R"]
    inner_face: Integer[np.ndarray, "*R"]
    inner_bary: Float[np.ndarray, "*R 3"]
    uv_inner: Float[np.ndarray, "*R 2"]
    inner_depth: Float[np.ndarray, "*R"]
    outer_hit: Bool[np.ndarray, "*R"]
    outer_face: Integer[np.ndarray, "*R"]
    outer_bary: Float[np.ndarray, "*R 3"]
    uv_outer: Float[np.ndarray, "*R 2"]
    outer_depth: Float[np.ndarray, "*R"]
    outer_exit_hit: Bool[np.ndarray, "*R"]
    outer_exit_face: Integer[np.ndarray, "*R"]
    outer_exit_bary: Float[np.ndarray, "*R 3"]
    uv_outer_exit: Float[np.ndarray, "*R 2"]
    outer_exit_depth: Float[np.ndarray, "*R"]
    pixels: Integer[np.ndarray, "N 2"] | None = None

    def reshaped(self, shape: tuple[int, ...]) -> "RaycastHits":
        """The same hits with the ray dimensions reshaped to ``shape`` (pixels kept)."""
        out = {}
        for f in fields(self):
            a = getattr(self, f.name)
            if f.name == "pixels" or a is None:
                out[f.name] = a
            else:
                vector = f.name.endswith("bary") or f.name.startswith("uv_")  # trailing (3,) / (2,)
                out[f.name] = a.reshape(*shape, a.shape[-1]) if vector else a.reshape(shape)
        return RaycastHits(**out)


def uv_inner_or_exit(hits: RaycastHits) -> tuple[Float[np.ndarray, "*R 2"], Bool[np.ndarray, "*R"]]:
    """The DELIFFAS inner sample: the inner hit's uv, or the outer exit's uv where the ray misses.

    A ray that misses the inner surface but crosses the outer shell samples the shell's second
    (exit) hit in place of the inner surface (dynacap-formats.md 3.4, ``run.py``).

    Returns:
        uv (R, 2) float32 (NaN where neither exists) and inner_from_outer (R,) bool, True where
        the uv came from the outer exit hit.
    """
    inner_from_outer = ~hits.inner_hit & hits.outer_exit_hit
    uv = np.where(inner_from_outer[..., None], hits.uv_outer_exit, hits.uv_inner)
    return uv, inner_from_outer


def _box_candidates(origins: np.ndarray, directions: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Indices (M,) int64 of the rays whose half-line t >= 0 meets the box [lo, hi].

    Slab test in the inputs' precision, in cache-sized chunks (no (N, .) temporaries). A NaN
    (0 x inf for a zero direction component with the origin on a slab plane, or a NaN ray) makes
    the final comparison False, so such rays are kept: the test only ever keeps too many rays,
    never too few.

    Args:
        origins, directions: (N, 3) float.
        lo, hi: (3,) float box corners.
    """
    n = len(origins)
    keep = np.empty(n, bool)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for start in range(0, n, _BOX_CHUNK):
            o = origins[start : start + _BOX_CHUNK]
            d = directions[start : start + _BOX_CHUNK]
            for k in range(3):  # per axis: numpy reductions over a length-3 axis are slow
                inv = 1.0 / d[:, k]  # (n,), +-inf for a zero component
                a = (lo[k] - o[:, k]) * inv
                b = (hi[k] - o[:, k]) * inv
                if k == 0:
                    t_near, t_far = np.minimum(a, b), np.maximum(a, b)
                else:  # NaN-propagating
                    np.maximum(t_near, np.minimum(a, b), out=t_near)
                    np.minimum(t_far, np.maximum(a, b), out=t_far)
            keep[start : start + _BOX_CHUNK] = ~((t_far < t_near) | (t_far < 0))
    return np.flatnonzero(keep)


def projected_pixel_window(camera: Camera, points: Real[np.ndarray, "N 3"], pad: float = 1.0
                           ) -> tuple[int, int, int, int] | None:
    """The pixels whose ray can meet the convex hull of ``points``: a window [c0, c1) x [r0, r1).

    For a pinhole camera and points strictly in front of it (camera z > 0), a triangle projects
    to the triangle of its projected corners, so every ray that meets the hull passes through the
    box of the projected points; the window holds the pixels whose centre (col + 0.5, row + 0.5)
    lies in that box grown by ``pad`` pixels (round-off margin), clipped to the image.

    Args:
        camera: the camera.
        points: (N, 3) world mm.
        pad: margin in pixels.

    Returns:
        (c0, r0, c1, r1) with 0 <= c0 <= c1 <= W and 0 <= r0 <= r1 <= H (possibly empty), or None
        when some point is not in front of the camera or not finite: the projection then does not
        bound the hull and every pixel must be cast.
    """
    check_shape("points", points, "N 3")
    if len(points) == 0:
        return 0, 0, 0, 0
    points = np.asarray(points, np.float64)
    proj = camera.K @ camera.world_to_cam[:3]  # (3, 4)
    # homogeneous image coordinates column by column (an (N, 3) @ (3, 3) product goes through
    # multi-threaded BLAS, slower here than the arithmetic); reductions on 1-D columns
    hom = [points[:, 0] * proj[j, 0] + points[:, 1] * proj[j, 1] + points[:, 2] * proj[j, 2] + proj[j, 3] for j in range(3)]
    z = points[:, 0] * camera.R[2, 0] + points[:, 1] * camera.R[2, 1] + points[:, 2] * camera.R[2, 2] + camera.t[2]
    if not z.min() > 0:  # also False for NaN
        return None
    col, row = hom[0] / hom[2], hom[1] / hom[2]
    lo = (float(col.min()) - pad, float(row.min()) - pad)
    hi = (float(col.max()) + pad, float(row.max()) + pad)
    if not all(math.isfinite(v) for v in (*lo, *hi)):
        return None
    # centre k + 0.5 in [lo, hi]  <=>  ceil(lo - 0.5) <= k <= floor(hi - 0.5)
    c0, r0 = (max(0, int(math.ceil(v - 0.5))) for v in lo)
    c1 = min(camera.width, max(0, int(math.floor(hi[0] - 0.5)) + 1))
    r1 = min(camera.height, max(0, int(math.floor(hi[1] - 0.5)) + 1))
    return min(c0, c1), min(r0, r1), c1, r1


def _put_rows(out: np.ndarray, idx: np.ndarray, values: np.ndarray) -> None:
    """``out[idx] = values`` for C-contiguous (n, ...) ``out``; rows of 2-D arrays are moved as one
    opaque item each (numpy's multi-dimensional fancy assignment is several times slower)."""
    if out.ndim == 1:
        out[idx] = values
        return
    row = np.dtype((np.void, out.itemsize * math.prod(out.shape[1:])))
    out.view(row).reshape(len(out))[idx] = np.ascontiguousarray(values, out.dtype).view(row).reshape(len(values))


def _scatter(n: int, idx: np.ndarray, values: np.ndarray, fill) -> np.ndarray:
    """(n, ...) array of ``fill`` with ``values`` (M, ...) written at rows ``idx`` (M,)."""
    if len(idx) == n:
        return values
    shape = (n, *values.shape[1:])
    # zeros come from calloc: pages holding no written row are never touched
    out = np.zeros(shape, values.dtype) if fill == 0 else np.full(shape, fill, values.dtype)
    _put_rows(out, idx, values)
    return out


def _interp_uv(corner_uvs: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """uv (N, 2) float32 = sum_k bary_k * corner_uvs[face, k]; NaN where face < 0."""
    miss = face < 0
    uv = np.empty((len(face), 2), np.float32)
    if len(corner_uvs) == 0 or miss.all():
        uv.fill(np.nan)
        return uv
    c = np.take(corner_uvs.reshape(-1, 6), np.where(miss, 0, face), axis=0)  # (N, 6): u0 v0 u1 v1 u2 v2
    for j in range(2):
        uv[:, j] = bary[:, 0] * c[:, j] + bary[:, 1] * c[:, 2 + j] + bary[:, 2] * c[:, 4 + j]
        uv[:, j][miss] = np.nan
    return uv


class UVRaycaster:
    """Ray casting scenes of one frame's inner and outer surfaces, reused across cameras.

    Args:
        inner_verts: (V, 3) float, mm, the posed mesh.
        faces: (F, 3) int, shared by both surfaces.
        outer_verts: (V, 3) float, mm, the offset shell (same faces and uvs).
        atlas: UVAtlas with ``face_uvs`` (F, 3).
        peel: "recast" (cast again from just beyond the first outer hit) or "list" (open3d
            ``list_intersections`` and the two nearest distinct hits). Both give the same hits;
            "recast" is the faster on the DDC template (docs/geometry.md).
    """

    def __init__(
        self,
        inner_verts: Real[ArrayLike, "V 3"],
        faces: Integer[ArrayLike, "F 3"],
        outer_verts: Real[ArrayLike, "V 3"],
        atlas: UVAtlas,
        *,
        peel: PeelMethod = "recast",
    ) -> None:
        sizes = check_shape("inner_verts", inner_verts, "V 3")
        sizes = check_shape("faces", faces, "F 3", sizes)
        check_shape("outer_verts", outer_verts, "V 3", sizes)
        if atlas.num_faces != sizes["F"]:
            raise ValueError(f"atlas: face_uvs has {atlas.num_faces} rows, faces has {sizes['F']}")
        if peel not in ("recast", "list"):
            raise ValueError(f"peel: expected 'recast' or 'list', got {peel!r}")
        inner_verts, faces, outer_verts = to_numpy(inner_verts), to_numpy(faces), to_numpy(outer_verts)
        self.peel = peel
        # the frame's surfaces as given (read by fast.frame's rasteriser of the same frame)
        self.inner_verts, self.outer_verts, self.faces, self.atlas = inner_verts, outer_verts, faces, atlas
        self.corner_uvs = atlas.uvs.astype(np.float32)[atlas.face_uvs]  # (F, 3, 2) float32
        # open3d scenes built at the first cast: the rasterising fast path never casts
        self._scenes: tuple | None = None
        self._scenes_lock = threading.Lock()
        ov = np.asarray(outer_verts, dtype=np.float64)
        diag = float(np.linalg.norm(ov.max(0) - ov.min(0))) if len(ov) else 1.0
        self.peel_eps = PEEL_EPS_REL * max(diag, 1e-6)
        both = np.concatenate([np.asarray(inner_verts, np.float64), ov])
        pad = BOX_PAD_REL * max(diag, 1e-6)
        # (3,) float64 corners of the padded box around both surfaces; empty meshes: an empty box
        self.hull_points = both  # (2V, 3) float64: every ray that meets a surface meets their hull
        self.box_lo = both.min(0) - pad if len(both) else np.full(3, np.inf)
        self.box_hi = both.max(0) + pad if len(both) else np.full(3, -np.inf)

    def _built_scenes(self) -> tuple:
        if self._scenes is None:
            with self._scenes_lock:  # frames may render in several threads with one raycaster
                if self._scenes is None:
                    self._scenes = (build_scene(self.inner_verts, self.faces), build_scene(self.outer_verts, self.faces))
        return self._scenes

    @property
    def inner_scene(self):
        """The open3d ray casting scene of the inner surface (built on first use)."""
        return self._built_scenes()[0]

    @property
    def outer_scene(self):
        """The open3d ray casting scene of the outer surface (built on first use)."""
        return self._built_scenes()[1]

    def cast_rays(self, origins: Real[np.ndarray, "N 3"], directions: Real[np.ndarray, "N 3"]) -> RaycastHits:
        """Hits of arbitrary rays: origins (N, 3) mm and unit directions (N, 3); flat (N,) hits.

        Only the rays that meet the (padded) bounding box of both surfaces are handed to open3d;
        the others miss both surfaces by construction (see ``_box_candidates``).
        """
        check_shape("origins", origins, "N 3")
        check_shape("directions", directions, "N 3", {"N": len(origins)})
        origins, directions = np.asarray(origins), np.asarray(directions)
        n = len(origins)
        cand = _box_candidates(origins, directions, self.box_lo, self.box_hi)  # (M,) int64 ray indices
        sub = _rays(np.take(origins, cand, axis=0), np.take(directions, cand, axis=0))  # (M, 6) float32
        hits = self._hits(self._cast_packed(sub))
        fills = {"hit": False, "face": -1, "bary": 0.0, "depth": np.inf}
        out = {}
        for name, values in hits.items():
            fill = np.nan if name.startswith("uv_") else fills[name.rsplit("_", 1)[1]]
            out[name] = _scatter(n, cand, values, fill)
        return RaycastHits(**out)

    def _cast_packed(self, rays: np.ndarray, exits: ExitRays = "all") -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Raw hits (t, face, bary) of (M, 6) float32 packed rays for "inner", "outer" and
        "outer_exit" (no culling, no uvs); with ``exits="inner_miss"`` the "recast" peel looks
        for exits only on the rays that miss the inner surface."""
        ti, fi, bi = _cast(self.inner_scene, rays)
        if self.peel == "list":
            to, fo, bo, te, fe, be = self._peel_list(rays)
            return {"inner": (ti, fi, bi), "outer": (to, fo, bo), "outer_exit": (te, fe, be)}
        to, fo, bo = _cast(self.outer_scene, rays)
        te = np.full_like(to, np.inf)
        fe = np.full_like(fo, -1)
        be = np.zeros_like(bo)
        hit = np.flatnonzero((fo >= 0) & (fi < 0)) if exits == "inner_miss" else np.flatnonzero(fo >= 0)
        step = to[hit] + np.float32(self.peel_eps)  # (n,)
        again = np.take(rays, hit, axis=0)  # (n, 6)
        again[:, :3] += step[:, None] * again[:, 3:]
        t2, f2, b2 = _cast(self.outer_scene, again)
        te[hit], fe[hit] = t2 + step, f2
        _put_rows(be, hit, b2)
        return {"inner": (ti, fi, bi), "outer": (to, fo, bo), "outer_exit": (te, fe, be)}

    def _hits(self, raw: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """RaycastHits fields (M,) of raw hits, or of their ``rows`` only (uvs are interpolated
        after the selection)."""
        out = {}
        for name, (t, f, b) in raw.items():
            if rows is not None:
                t, f, b = np.take(t, rows), np.take(f, rows), np.take(b, rows, axis=0)
            out[f"{name}_hit"] = f >= 0
            out[f"{name}_face"] = f
            out[f"{name}_bary"] = b
            out[f"uv_{name}"] = _interp_uv(self.corner_uvs, f, b)
            out[f"{name}_depth"] = t
        return out

    def _peel_list(self, rays: np.ndarray):
        n = len(rays)
        ray_ids, t, face, bary = _all_hits(self.outer_scene, rays)
        out = []
        first = np.ones(len(ray_ids), bool)
        first[1:] = ray_ids[1:] != ray_ids[:-1]
        first_idx = np.flatnonzero(first)
        # second: the next hit of the same ray farther than peel_eps from the first
        t_first = np.repeat(t[first_idx], np.diff(np.append(first_idx, len(ray_ids))))
        later = ~first & (t > t_first + self.peel_eps)
        later_idx = np.flatnonzero(later)
        if len(later_idx):
            keep = np.ones(len(later_idx), bool)
            keep[1:] = ray_ids[later_idx[1:]] != ray_ids[later_idx[:-1]]
            second_idx = later_idx[keep]
        else:
            second_idx = later_idx
        for idx in (first_idx, second_idx):
            tt = np.full(n, np.inf, np.float32)
            ff = np.full(n, -1, np.int64)
            bb = np.zeros((n, 3), np.float32)
            r = ray_ids[idx]
            tt[r], ff[r], bb[r] = t[idx], face[idx], bary[idx]
            out += [tt, ff, bb]
        return out

    def cast(self, camera: Camera, mask: Shaped[np.ndarray, "H W"] | None = None) -> RaycastHits:
        """Hits of the rays through pixel centres of ``camera``.

        Args:
            camera: the camera (pixel (c, r) is sampled at (c + 0.5, r + 0.5)).
            mask: optional (H, W) bool, e.g. a foreground mask; only those pixels are cast.

        Returns:
            RaycastHits with (H, W) fields, or (N,) fields and ``pixels`` (N, 2) (col, row) in
            row-major order for a mask.
        """
        if mask is None:
            origins, dirs = camera.rays()
            return self.cast_rays(origins, dirs).reshaped((camera.height, camera.width))
        check_shape("mask", mask, f"{camera.height} {camera.width}")
        rows, cols = np.nonzero(np.asarray(mask, bool))
        pixels = np.stack([cols, rows], axis=1).astype(np.int64)
        origins, dirs = camera.rays(pixels + 0.5)
        hits = self.cast_rays(origins, dirs)
        return RaycastHits(**{**{f.name: getattr(hits, f.name) for f in fields(hits)}, "pixels": pixels})

    def cast_foreground(self, camera: Camera, exits: ExitRays = "all", fraction: float = 1.0,
                        rng: np.random.Generator | None = None) -> RaycastHits:
        """Hits of the pixels of ``camera`` whose ray meets either surface, without full-image arrays.

        Only the pixels in the projected window of both surfaces (``projected_pixel_window``)
        are cast; where that window is undefined (a vertex behind the camera) every pixel is
        cast, culled by the bounding box as in ``cast_rays``. The result equals ``cast(camera)``
        restricted to the pixels with ``inner_hit | outer_hit``.

        Args:
            camera: the camera.
            exits: "all", or "inner_miss" to peel the outer exit only where the ray misses the
                inner surface, the only place DELIFFAS uses it (``uv_inner_or_exit``); elsewhere
                ``outer_exit_hit`` is then False. Saves most of the third cast. The "list"
                peel method always finds every exit.
            fraction: cast each candidate pixel with this probability (a uniform random subset of the
                result, for a training step that shades only some rays); 1 = every pixel.
            rng: the draw's generator (needed when ``fraction`` < 1).

        Returns:
            RaycastHits with (N,) fields and ``pixels`` (N, 2) int64 (col, row) in row-major
            order.
        """
        if exits not in ("all", "inner_miss"):
            raise ValueError(f"exits: expected 'all' or 'inner_miss', got {exits!r}")
        window = projected_pixel_window(camera, self.hull_points)
        c0, r0, c1, r1 = window if window is not None else (0, 0, camera.width, camera.height)
        cols, rows = np.meshgrid(np.arange(c0, c1, dtype=np.int64), np.arange(r0, r1, dtype=np.int64))
        pixels = np.stack([cols.reshape(-1), rows.reshape(-1)], axis=1)  # (M, 2) row-major
        origins, dirs = camera.rays(pixels + 0.5)
        if window is None:
            cand = _box_candidates(origins, dirs, self.box_lo, self.box_hi)
            pixels = np.take(pixels, cand, axis=0)
            origins, dirs = np.take(origins, cand, axis=0), np.take(dirs, cand, axis=0)
        if fraction < 1:
            if rng is None or not fraction > 0:
                raise ValueError(f"fraction: expected a number in (0, 1] and an rng, got {fraction!r}, rng {rng!r}")
            pick = np.flatnonzero(rng.random(len(pixels)) < fraction)  # row-major order kept
            pixels = np.take(pixels, pick, axis=0)
            origins, dirs = np.take(origins, pick, axis=0), np.take(dirs, pick, axis=0)
        raw = self._cast_packed(_rays(origins, dirs), exits)
        keep = np.flatnonzero((raw["inner"][1] >= 0) | (raw["outer"][1] >= 0))
        return RaycastHits(**self._hits(raw, keep), pixels=np.take(pixels, keep, axis=0))

    def cast_batch(self, cameras: Sequence[Camera]) -> RaycastHits:
        """Full-image hits of several cameras of the same size in one pass: (C, H, W) fields."""
        if not cameras:
            raise ValueError("cast_batch: no cameras")
        size = (cameras[0].height, cameras[0].width)
        if any((c.height, c.width) != size for c in cameras):
            raise ValueError("cast_batch: cameras differ in image size; cast them one by one")
        rays = [c.rays() for c in cameras]
        origins = np.concatenate([r[0] for r in rays])
        dirs = np.concatenate([r[1] for r in rays])
        return self.cast_rays(origins, dirs).reshaped((len(cameras), *size))
