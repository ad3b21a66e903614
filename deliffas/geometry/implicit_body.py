"""Implicit bodies: signed-distance primitives (round cones, ellipsoids), their smooth union, and its
sampling on a grid for meshing (``deliffas.geometry.marching_tets``).

Shared by the procedural DDC character (``deliffas.geometry.procedural``) and the procedural body in
SMPL layout (``deliffas.geometry.smpl_body``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Primitive", "smooth_min", "sdf_grid"]


@dataclass(frozen=True)
class Primitive:
    """One SDF primitive: a round cone (a, b, ra, rb) or an oriented ellipsoid (c, R, radii)."""
    part: str
    kind: str
    a: np.ndarray
    b: np.ndarray | None = None
    ra: float = 0.0
    rb: float = 0.0
    rot: np.ndarray | None = None  # (3, 3) columns = ellipsoid axes
    radii: np.ndarray | None = None

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """(N,) approximate signed distance of points p (N, 3), mm (negative inside)."""
        if self.kind == "cone":
            ab = self.b - self.a
            t = np.clip(((p - self.a) @ ab) / (ab @ ab), 0.0, 1.0)
            q = p - (self.a + t[:, None] * ab)
            return np.linalg.norm(q, axis=1) - (self.ra + t * (self.rb - self.ra))
        loc = (p - self.a) @ self.rot  # coordinates along the ellipsoid axes
        k0 = np.linalg.norm(loc / self.radii, axis=1)
        k1 = np.linalg.norm(loc / self.radii ** 2, axis=1)
        return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self.kind == "cone":
            lo = np.minimum(self.a - self.ra, self.b - self.rb)
            hi = np.maximum(self.a + self.ra, self.b + self.rb)
            return lo, hi
        ext = np.abs(self.rot) @ self.radii
        return self.a - ext, self.a + ext


def smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (blend radius k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def sdf_grid(prims: list[Primitive], spacing: float, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth-union SDF sampled on a regular grid covering all primitives.

    Returns:
        values (nx, ny, nz) float64 and origin (3,) of grid point (0, 0, 0).
    """
    lows, highs = zip(*(p.bounds() for p in prims))
    margin = k + 3 * spacing
    lo = np.min(lows, axis=0) - margin
    hi = np.max(highs, axis=0) + margin
    n = np.ceil((hi - lo) / spacing).astype(int) + 1
    values = np.full(tuple(n), 1e6)
    axes = [lo[d] + spacing * np.arange(n[d]) for d in range(3)]
    for prim in prims:  # each primitive only touches its own bounding box (+ blend margin)
        plo, phi = prim.bounds()
        i0 = np.clip(np.floor((plo - k - lo) / spacing).astype(int), 0, n - 1)
        i1 = np.clip(np.ceil((phi + k - lo) / spacing).astype(int) + 1, 1, n)
        gx, gy, gz = np.meshgrid(axes[0][i0[0]:i1[0]], axes[1][i0[1]:i1[1]], axes[2][i0[2]:i1[2]], indexing="ij")
        pts = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
        block = values[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]]
        d = prim.sdf(pts).reshape(block.shape)
        values[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]] = smooth_min(block, d, k)
    return values, lo
