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
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal, Sequence

import numpy as np

from deliffas.checks import check_shape
from deliffas.data.cameras import Camera
from deliffas.geometry.atlas import UVAtlas

__all__ = [
    "RaycastHits",
    "UVRaycaster",
    "uv_inner_or_exit",
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

PeelMethod = Literal["recast", "list"]


def _o3d():
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - hard dependency, but may miss system libs
        raise ImportError(
            "deliffas.geometry.raycast needs the 'open3d' package (and its system libraries, "
            "see scripts/system_deps.sh)"
        ) from exc
    return o3d


def build_scene(verts: np.ndarray, faces: np.ndarray):
    """An open3d ``RaycastingScene`` holding one triangle mesh (float32 positions).

    Args:
        verts: (V, 3) float, mm.
        faces: (F, 3) int.
    """
    check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
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
    bary = np.empty((len(t), 3), np.float32)
    bary[:, 1:] = b12
    bary[:, 0] = 1.0 - b12[:, 0] - b12[:, 1]
    bary[miss] = 0.0
    return t, face, bary


def first_hits(scene, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def all_hits(scene, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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

    inner_hit: np.ndarray
    inner_face: np.ndarray
    inner_bary: np.ndarray
    uv_inner: np.ndarray
    inner_depth: np.ndarray
    outer_hit: np.ndarray
    outer_face: np.ndarray
    outer_bary: np.ndarray
    uv_outer: np.ndarray
    outer_depth: np.ndarray
    outer_exit_hit: np.ndarray
    outer_exit_face: np.ndarray
    outer_exit_bary: np.ndarray
    uv_outer_exit: np.ndarray
    outer_exit_depth: np.ndarray
    pixels: np.ndarray | None = None

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


def uv_inner_or_exit(hits: RaycastHits) -> tuple[np.ndarray, np.ndarray]:
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


def _interp_uv(corner_uvs: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """uv (N, 2) float32 = sum_k bary_k * corner_uvs[face, k]; NaN where face < 0."""
    uv = np.full((len(face), 2), np.nan, np.float32)
    hit = np.flatnonzero(face >= 0)
    c = corner_uvs[face[hit]]  # (n, 3, 2)
    b = bary[hit]
    uv[hit] = b[:, 0:1] * c[:, 0] + b[:, 1:2] * c[:, 1] + b[:, 2:3] * c[:, 2]
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
        inner_verts: np.ndarray,
        faces: np.ndarray,
        outer_verts: np.ndarray,
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
        self.peel = peel
        self.corner_uvs = atlas.corner_uvs.astype(np.float32)  # (F, 3, 2)
        self.inner_scene = build_scene(inner_verts, faces)
        self.outer_scene = build_scene(outer_verts, faces)
        ov = np.asarray(outer_verts, dtype=np.float64)
        diag = float(np.linalg.norm(ov.max(0) - ov.min(0))) if len(ov) else 1.0
        self.peel_eps = PEEL_EPS_REL * max(diag, 1e-6)

    def cast_rays(self, origins: np.ndarray, directions: np.ndarray) -> RaycastHits:
        """Hits of arbitrary rays: origins (N, 3) mm and unit directions (N, 3); flat (N,) hits."""
        check_shape("origins", origins, "N 3")
        check_shape("directions", directions, "N 3", {"N": len(origins)})
        rays = _rays(origins, directions)  # (N, 6) float32
        ti, fi, bi = _cast(self.inner_scene, rays)
        if self.peel == "recast":
            to, fo, bo = _cast(self.outer_scene, rays)
            te = np.full_like(to, np.inf)
            fe = np.full_like(fo, -1)
            be = np.zeros_like(bo)
            hit = np.flatnonzero(fo >= 0)
            step = to[hit] + np.float32(self.peel_eps)  # (n,)
            again = rays[hit]
            again[:, :3] += step[:, None] * again[:, 3:]
            t2, f2, b2 = _cast(self.outer_scene, again)
            te[hit], fe[hit], be[hit] = t2 + step, f2, b2
        else:
            to, fo, bo, te, fe, be = self._peel_list(rays)
        return RaycastHits(
            inner_hit=fi >= 0, inner_face=fi, inner_bary=bi,
            uv_inner=_interp_uv(self.corner_uvs, fi, bi), inner_depth=ti,
            outer_hit=fo >= 0, outer_face=fo, outer_bary=bo,
            uv_outer=_interp_uv(self.corner_uvs, fo, bo), outer_depth=to,
            outer_exit_hit=fe >= 0, outer_exit_face=fe, outer_exit_bary=be,
            uv_outer_exit=_interp_uv(self.corner_uvs, fe, be), outer_exit_depth=te,
        )  # fmt: skip

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

    def cast(self, camera: Camera, mask: np.ndarray | None = None) -> RaycastHits:
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
