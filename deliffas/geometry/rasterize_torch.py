"""Rasterised uvs of the inner and outer surfaces in torch, on any device (the GPU path's ``uv`` stage).

The same shaded pixels and uvs as :class:`deliffas.fast.rasterize.UVRasterizer` (whose numpy version
is the reference), computed with tensor operations only, so they run where the model runs (CUDA, or the
CPU) with no ray casting and no C kernel:

* fragments: every pixel centre (col + 0.5, row + 0.5) in each triangle's bounding box, kept where it
  lies inside or on the triangle's projection (both orientations), in chunks of ``CHUNK`` pairs;
* depth: a packed int64 key per fragment, (0x7FFFFFFF - bits of float32 1 / camera z) << 32 | face, so
  the smallest key is the nearest fragment and, at equal depth, the lowest face (the C kernel's order);
  one ``scatter_reduce(amin)`` per surface gives the first hit;
* peeling: on the pixels the inner surface misses, two more ``amin`` passes over the outer fragments
  with a key above the previous layer's give the second and third outer fragments; the exit is the
  first of them more than ``peel_eps`` (mm, along the ray) beyond the first, as the C kernel's;
* uvs: perspective-correct barycentrics of the chosen faces at the pixel centres (float64), per-corner
  atlas uvs interpolated with them.

Everything is computed in float64 except the stored depth (float32, as the kernel stores it), so the
pixels equal the kernel's up to the round-off of the projection's matrix products. A vertex behind the
camera makes the projection meaningless: :meth:`TorchUVRasterizer.shaded_pixels` then returns None and
the caller ray-casts (as ``UVRasterizer``).
"""

from __future__ import annotations


import numpy as np
import torch

from deliffas.checks import check_shape
from deliffas.geometry.arrays import ArrayLike, to_torch
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import PEEL_EPS_REL
from deliffas.geometry.shaded_pixels import ShadedPixels
from deliffas.io.cameras import Camera

__all__ = ["TorchUVRasterizer", "CHUNK"]

CHUNK = 1 << 22
"""(triangle, pixel) pairs tested at once: bounds the temporaries (about 40 bytes a pair)."""

_NONE = torch.iinfo(torch.int64).max  # empty key: no fragment
_LOW32 = 0xFFFFFFFF
_MAX_BITS = 0x7FFFFFFF


class TorchUVRasterizer:
    """One frame's inner and outer surfaces, rasterised per camera in torch on ``device``.

    Args:
        inner_verts: (V, 3) float, mm, the posed mesh (numpy or a tensor on any device).
        faces: (F, 3) int, shared by both surfaces.
        outer_verts: (V, 3) float, mm, the offset shell.
        atlas: UVAtlas with ``face_uvs`` (F, 3).
        device: where the rasterising runs and the results live.
    """

    def __init__(self, inner_verts: ArrayLike, faces: ArrayLike, outer_verts: ArrayLike, atlas: UVAtlas,
                 device: torch.device | str = "cpu") -> None:
        sizes = check_shape("inner_verts", inner_verts, "V 3")
        sizes = check_shape("faces", faces, "F 3", sizes)
        check_shape("outer_verts", outer_verts, "V 3", sizes)
        if atlas.num_faces != sizes["F"]:
            raise ValueError(f"atlas: face_uvs has {atlas.num_faces} rows, faces has {sizes['F']}")
        self.device = torch.device(device)
        self.atlas = atlas
        f64 = dict(dtype=torch.float64, device=self.device)
        self.inner = to_torch(inner_verts).to(**f64)
        self.outer = to_torch(outer_verts).to(**f64)
        self.faces = to_torch(faces).to(dtype=torch.int64, device=self.device)
        corner = np.asarray(atlas.uvs, np.float32)[np.asarray(atlas.face_uvs)].reshape(-1, 6)
        self.corner_uvs = torch.from_numpy(np.ascontiguousarray(corner)).to(**f64)  # (F, 6) u0 v0 u1 v1 u2 v2
        if len(self.outer):  # as UVRasterizer: PEEL_EPS_REL x the outer surface's box diagonal (a 0-d tensor)
            diag = torch.linalg.vector_norm(self.outer.max(0).values - self.outer.min(0).values)
        else:
            diag = torch.ones((), **f64)
        self.peel_eps = PEEL_EPS_REL * diag.clamp_min(1e-6)

    def _project(self, camera: Camera, verts: torch.Tensor) -> torch.Tensor:
        """(V, 3) float64 (x px, y px, camera z mm), as ``fast.rasterize._project``."""
        R = torch.as_tensor(camera.R, dtype=torch.float64, device=self.device)
        t = torch.as_tensor(camera.t, dtype=torch.float64, device=self.device)
        K = torch.as_tensor(np.asarray(camera.K, np.float64), device=self.device)
        cam = verts @ R.T + t
        img = cam @ K.T
        return torch.stack([img[:, 0] / img[:, 2], img[:, 1] / img[:, 2], cam[:, 2]], dim=1)

    def shaded_pixels(self, camera: Camera, viewdir: bool = True) -> ShadedPixels | None:
        """The shaded pixels of ``camera`` (tensors on the rasteriser's device), or None when a vertex is not in
        front of it (ray-cast then). ``viewdir=False`` leaves out the view directions."""
        pin, pout = self._project(camera, self.inner), self._project(camera, self.outer)
        if len(pin) and not bool(torch.cat([pin[:, 2], pout[:, 2]]).min() > 0):  # also False for NaN
            return None
        H, W = camera.height, camera.width
        n = H * W
        inner_key = _first_keys(pin, self.faces, H, W)
        pix, key = _fragments(pout, self.faces, H, W)
        outer_key = torch.full((n,), _NONE, dtype=torch.int64, device=self.device)
        outer_key.scatter_reduce_(0, pix, key, "amin")
        m = torch.as_tensor(camera.R.T @ np.linalg.inv(camera.K), dtype=torch.float64, device=self.device)
        exit_key = self._exit_keys(pix, key, outer_key, inner_key, W, m)
        has_outer = outer_key != _NONE
        from_outer = (inner_key == _NONE) & (exit_key != _NONE)
        shaded = torch.nonzero(has_outer & ((inner_key != _NONE) | from_outer)).squeeze(1)  # row-major
        x = (shaded % W).to(torch.float64) + 0.5
        y = (shaded // W).to(torch.float64) + 0.5
        fo = from_outer[shaded]
        src_key = torch.where(fo, exit_key[shaded], inner_key[shaded])
        src_face = src_key & _LOW32
        # the inner sample: the inner face on the inner surface, or the exit face on the outer surface
        uv_in = torch.where(fo[:, None], _face_uv(pout, self.faces, self.corner_uvs, src_face, x, y),
                            _face_uv(pin, self.faces, self.corner_uvs, src_face, x, y))
        uv_out = _face_uv(pout, self.faces, self.corner_uvs, outer_key[shaded] & _LOW32, x, y)
        dirs = None
        if viewdir:
            d = _ray_dirs(m, x, y)
            dirs = (d / torch.linalg.vector_norm(d, dim=1, keepdim=True)).to(torch.float32)
        return ShadedPixels(pixels=shaded, uv_inner=uv_in.to(torch.float32), inner_from_outer=fo,
                                 uv_outer=uv_out.to(torch.float32), viewdir=dirs)

    def _exit_keys(self, pix: torch.Tensor, key: torch.Tensor, outer_key: torch.Tensor, inner_key: torch.Tensor,
                   W: int, m: torch.Tensor) -> torch.Tensor:
        """(H W,) key of the outer exit where the inner surface is missed (else empty): the first of the
        second and third outer fragments farther than ``peel_eps`` along the ray beyond the first."""
        n = outer_key.shape[0]
        sel = (inner_key[pix] == _NONE) & (key != outer_key[pix])
        pix, key = pix[sel], key[sel]
        second = torch.full((n,), _NONE, dtype=torch.int64, device=self.device)
        second.scatter_reduce_(0, pix, key, "amin")
        later = key > second[pix]
        third = torch.full((n,), _NONE, dtype=torch.int64, device=self.device)
        third.scatter_reduce_(0, pix[later], key[later], "amin")
        p = torch.arange(n, device=self.device)
        x, y = (p % W).to(torch.float64) + 0.5, (p // W).to(torch.float64) + 0.5
        zmin = _depth(outer_key) + self.peel_eps / torch.linalg.vector_norm(_ray_dirs(m, x, y), dim=1)
        second_out = (second != _NONE) & (_depth(second) > zmin)
        third_out = (third != _NONE) & (_depth(third) > zmin)
        empty = torch.full_like(second, _NONE)
        return torch.where(second_out, second, torch.where(third_out, third, empty))


def _ray_dirs(m: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(N, 3) float64 unnormalised world directions m (x, y, 1) of pixel centres, summed as the C kernel."""
    return torch.stack([m[j, 0] * x + m[j, 1] * y + m[j, 2] for j in range(3)], dim=1)


def _depth(keys: torch.Tensor) -> torch.Tensor:
    """Camera z (float64, from the stored float32 1 / z) of packed keys; meaningless where empty."""
    bits = (_MAX_BITS - (keys >> 32)).clamp(0, _MAX_BITS).to(torch.int32)
    return 1.0 / bits.view(torch.float32).to(torch.float64)


def _first_keys(P: torch.Tensor, faces: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(H W,) the nearest fragment's key per pixel (``_NONE`` where none)."""
    pix, key = _fragments(P, faces, H, W)
    out = torch.full((H * W,), _NONE, dtype=torch.int64, device=P.device)
    return out.scatter_reduce_(0, pix, key, "amin")


def _fragments(P: torch.Tensor, faces: torch.Tensor, H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every covered (pixel, key) of a projected surface P (V, 3): flat pixel (M,) int64, packed key (M,) int64."""
    a, b, c = P[faces[:, 0]], P[faces[:, 1]], P[faces[:, 2]]  # (F, 3) each
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    xs, ys = torch.stack([a[:, 0], b[:, 0], c[:, 0]]), torch.stack([a[:, 1], b[:, 1], c[:, 1]])
    cs = torch.clamp(torch.ceil(xs.min(0).values - 0.5), min=0)
    ce = torch.clamp(torch.floor(xs.max(0).values - 0.5), max=W - 1)
    rs = torch.clamp(torch.ceil(ys.min(0).values - 0.5), min=0)
    re = torch.clamp(torch.floor(ys.max(0).values - 0.5), max=H - 1)
    ok = (area != 0) & torch.isfinite(area) & (ce >= cs) & (re >= rs)  # NaN compares False
    tri = torch.nonzero(ok).squeeze(1)
    nc, nr = (ce[tri] - cs[tri] + 1).to(torch.int64), (re[tri] - rs[tri] + 1).to(torch.int64)
    counts = nc * nr
    cum = torch.cumsum(counts, 0).cpu().numpy()  # one copy to the host: the chunks' bounds
    bounds = [0, *np.searchsorted(cum, np.arange(CHUNK, int(cum[-1]) if len(cum) else 0, CHUNK), side="right"),
              len(tri)]
    pix_parts, key_parts = [], []
    for start, stop in zip(bounds[:-1], bounds[1:]):
        if stop <= start:
            continue
        sel = slice(int(start), int(stop))
        cnt = counts[sel]
        total = int(cum[stop - 1] - (cum[start - 1] if start else 0))
        t = torch.repeat_interleave(tri[sel], cnt, output_size=total)
        first = torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt, output_size=total)
        offset = torch.arange(total, device=P.device) - first
        ncol = torch.repeat_interleave(nc[sel], cnt, output_size=total)
        col = cs[t].to(torch.int64) + offset % ncol
        row = rs[t].to(torch.int64) + offset // ncol
        inside, key = _cover(a[t], b[t], c[t], area[t], col, row, t)
        pix_parts.append(row[inside] * W + col[inside])
        key_parts.append(key)
    if not pix_parts:
        empty = torch.zeros(0, dtype=torch.int64, device=P.device)
        return empty, empty.clone()
    return torch.cat(pix_parts) if len(pix_parts) > 1 else pix_parts[0], torch.cat(key_parts)


def _cover(A: torch.Tensor, B: torch.Tensor, C: torch.Tensor, area: torch.Tensor, col: torch.Tensor,
           row: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Which pairs (triangle t with corners A, B, C (M, 3); pixel col, row (M,)) are covered: inside (M,) bool,
    and the covered pairs' keys. Screen-space weights and 1 / z as the C kernel computes them (the same
    operations in float64; 1 / z rounded to float32)."""
    x, y = col.to(torch.float64) + 0.5, row.to(torch.float64) + 0.5
    inv = 1.0 / area
    l0 = ((C[:, 0] - B[:, 0]) * (y - B[:, 1]) - (C[:, 1] - B[:, 1]) * (x - B[:, 0])) * inv
    l1 = ((A[:, 0] - C[:, 0]) * (y - C[:, 1]) - (A[:, 1] - C[:, 1]) * (x - C[:, 0])) * inv
    l2 = ((B[:, 0] - A[:, 0]) * (y - A[:, 1]) - (B[:, 1] - A[:, 1]) * (x - A[:, 0])) * inv
    inv_z = (l0 * (1.0 / A[:, 2]) + l1 * (1.0 / B[:, 2]) + l2 * (1.0 / C[:, 2])).to(torch.float32)
    inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0) & (inv_z > 0)
    bits = inv_z[inside].view(torch.int32).to(torch.int64)
    key = ((_MAX_BITS - bits) << 32) | t[inside]
    return inside, key


def _face_uv(P: torch.Tensor, faces: torch.Tensor, corner_uvs: torch.Tensor, face: torch.Tensor, x: torch.Tensor,
             y: torch.Tensor) -> torch.Tensor:
    """(M, 2) float64 perspective-correct uvs of faces (M,) at pixel centres (x, y) (M,), as
    ``fast.rasterize._face_uv``."""
    tri = faces[face]
    A, B, C = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    inv = 1.0 / ((B[:, 0] - A[:, 0]) * (C[:, 1] - A[:, 1]) - (B[:, 1] - A[:, 1]) * (C[:, 0] - A[:, 0]))
    q0 = ((C[:, 0] - B[:, 0]) * (y - B[:, 1]) - (C[:, 1] - B[:, 1]) * (x - B[:, 0])) * inv * (1.0 / A[:, 2])
    q1 = ((A[:, 0] - C[:, 0]) * (y - C[:, 1]) - (A[:, 1] - C[:, 1]) * (x - C[:, 0])) * inv * (1.0 / B[:, 2])
    q2 = ((B[:, 0] - A[:, 0]) * (y - A[:, 1]) - (B[:, 1] - A[:, 1]) * (x - A[:, 0])) * inv * (1.0 / C[:, 2])
    s = 1.0 / (q0 + q1 + q2)
    cu = corner_uvs[face]  # (M, 6)
    return torch.stack([(q0 * cu[:, 0] + q1 * cu[:, 2] + q2 * cu[:, 4]) * s,
                        (q0 * cu[:, 1] + q1 * cu[:, 3] + q2 * cu[:, 5]) * s], dim=1)
