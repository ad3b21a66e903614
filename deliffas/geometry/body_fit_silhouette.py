"""The silhouette terms of :func:`deliffas.geometry.body_fit.fit_body` and the IoU of a fitted body's silhouette.

Masks are downsampled once to ``mask_height`` (area average, then >= half covered); per view and frame:

* **outside**: the distance transform of the mask's complement (pixels, ``cv2.distanceTransform``, 0 inside the
  mask) is sampled bilinearly (``grid_sample``, differentiable) at every projected vertex: vertices outside the
  mask are pulled in;
* **cover**: a fixed random sample of pixels inside the mask; every few steps, the 8 projected vertices nearest each
  are searched, and whether it lies inside a projected triangle around the 4 nearest (covered by the body); each
  uncovered sample then pulls the nearest of its 8 vertices towards itself at every step: the body grows until it
  covers the mask.

Pixel distances become mm at the body's depth in that view (``depth / focal``), so both terms are in cm^2 as the
keypoint term, robust (Geman-McClure). Views whose mask is empty weigh 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree
from jaxtyping import Bool, Float, Float64, Integer, Shaped
from torch import Tensor

from deliffas.io.cameras import Camera

__all__ = ["SilhouetteTargets", "binary_masks", "prepare_silhouettes", "project", "silhouette_terms",
           "nearest_candidates", "vertex_face_table", "covered_samples", "mm_per_pixel", "rasterize_silhouettes",
           "silhouette_iou", "CANDIDATES", "COVER_TEST", "SUPERSAMPLE"]

CANDIDATES = 8
"""Nearest projected vertices kept per mask sample between two searches."""
COVER_TEST = 4
"""Nearest projected vertices whose triangles are tested for containing a mask sample (is it covered?)."""
SUPERSAMPLE = 4
"""``rasterize_silhouettes`` fills the triangles at this many times the resolution, then keeps the pixels at least
half covered (area average): the silhouette's boundary pixels follow the pixel-centre rule within 1/8 pixel."""
_SEARCH_CHUNK = 1 << 24
"""Elements of the temporaries of the covered-sample test at once (64 MB of float32)."""
_MIN_DEPTH_MM = 1.0
"""Vertices closer to (or behind) a camera's plane do not count in its silhouette terms."""


@dataclass(frozen=True)
class SilhouetteTargets:
    """The masks of N frames x C cameras, prepared once for the silhouette terms.

    Attributes:
        proj: (C, 3, 4) world mm -> homogeneous pixels of the downsampled masks (K scaled, corner convention).
        focal: (C,) mean of fx and fy of the scaled K, pixels.
        masks: (N, C, h, w) bool downsampled masks.
        dist: (N * C, 1, h, w) distance of each pixel to the mask in pixels (0 inside), the terms' dtype/device.
        samples: (N, C, S, 2) pixel coordinates (col, row) of the random samples inside each mask.
        view_weight: (N, C) 1 where the mask has pixels, else 0.
    """

    proj: Float[Tensor, "C 3 4"]
    focal: Float[Tensor, "C"]
    masks: Bool[np.ndarray, "N C h w"]
    dist: Float[Tensor, "NC 1 h w"]
    samples: Float[Tensor, "N C S 2"]
    view_weight: Float[Tensor, "N C"]


def binary_masks(masks: Shaped[np.ndarray, "N C H W"], height: int) -> Bool[np.ndarray, "N C h w"]:
    """Masks as bool, downsampled to ``height`` rows (area average, kept where >= half covered; never upsampled).

    ``uint8`` masks whose values exceed 1 are alphas (inside: > 127); others are inside where non-zero.
    """
    masks = np.asarray(masks)
    threshold = 127 if masks.dtype == np.uint8 and masks.size and int(masks.max()) > 1 else 0
    N, C, H, W = masks.shape
    if H <= height:
        return masks > threshold
    h, w = int(height), max(1, int(round(W * height / H)))
    out = np.empty((N, C, h, w), bool)
    for n in range(N):  # one image at a time: the full-resolution masks can be large
        for c in range(C):
            full = (masks[n, c] > threshold).view(np.uint8)
            out[n, c] = cv2.resize(full, (w, h), interpolation=cv2.INTER_AREA) > 0
    return out


def _projections(cameras: Sequence[Camera], full: tuple[int, int], size: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(C, 3, 4) float64 ``K' [R | t]`` of each camera for masks of ``size`` (h, w) given at ``full`` (H, W), and
    (C,) the mean focal length of ``K'``."""
    (H, W), (h, w) = full, size
    out, focal = [], []
    for cam in cameras:
        if abs(W / H - cam.width / cam.height) > 0.02 * cam.width / cam.height:
            raise ValueError(f"fit_body: masks of {W}x{H} do not have the aspect of camera {cam.name} "
                             f"({cam.width}x{cam.height})")
        K = cam.rescaled(w, h).K
        out.append(K @ cam.world_to_cam[:3])
        focal.append(0.5 * (K[0, 0] + K[1, 1]))
    return np.stack(out), np.asarray(focal)


def prepare_silhouettes(masks: Shaped[np.ndarray, "N C H W"], cameras: Sequence[Camera], height: int, samples: int,
                        seed: int, like: Tensor) -> SilhouetteTargets:
    """Downsample the masks, their distance transforms and random samples inside them.

    Args:
        masks: (N, C, H, W) person masks (see :func:`binary_masks`), any resolution with the cameras' aspect.
        cameras: the C cameras.
        height: rows of the downsampled masks.
        samples: S pixels drawn per mask (with replacement when the mask is smaller).
        seed: seed of the draw.
        like: a tensor whose dtype and device the tensors take.
    """
    small = binary_masks(masks, height)
    N, C, h, w = small.shape
    proj, focal = _projections(cameras, masks.shape[2:], (h, w))
    rng = np.random.default_rng(seed)
    dist = np.zeros((N * C, 1, h, w), np.float32)
    pts = np.zeros((N, C, samples, 2), np.float32)
    weight = np.zeros((N, C), np.float32)
    for n in range(N):
        for c in range(C):
            rows, cols = np.nonzero(small[n, c])
            if not len(rows):
                continue
            weight[n, c] = 1.0
            dist[n * C + c, 0] = cv2.distanceTransform((~small[n, c]).view(np.uint8), cv2.DIST_L2, 5)
            pick = rng.integers(0, len(rows), samples)
            jitter = rng.uniform(0.0, 1.0, (samples, 2))
            pts[n, c] = np.stack([cols[pick], rows[pick]], axis=1) + jitter
    factory = dict(dtype=like.dtype, device=like.device)
    return SilhouetteTargets(torch.as_tensor(proj, **factory), torch.as_tensor(focal, **factory), small,
                             torch.as_tensor(dist, **factory), torch.as_tensor(pts, **factory),
                             torch.as_tensor(weight, **factory))


def project(points: Float[Tensor, "N P 3"], proj: Float[Tensor, "C 3 4"]
            ) -> tuple[Float[Tensor, "N C P 2"], Float[Tensor, "N C P"]]:
    """Pixel coordinates (col, row) and camera depth (mm) of world points (mm) in each camera."""
    hom = torch.einsum("cij,npj->ncpi", proj[:, :, :3], points) + proj[:, None, :, 3]  # (N, C, P, 3)
    depth = hom[..., 2]
    uv = hom[..., :2] / depth.clamp(min=_MIN_DEPTH_MM)[..., None]
    return uv, depth


def _view_chunks(views: int, per_view: int) -> list[slice]:
    """Chunks of views whose temporaries hold about ``_SEARCH_CHUNK`` elements (``per_view`` each)."""
    step = max(1, _SEARCH_CHUNK // max(per_view, 1))
    return [slice(i, i + step) for i in range(0, views, step)]


def nearest_candidates(uv: Float[Tensor, "N C V 2"], samples: Float[Tensor, "N C S 2"], k: int = CANDIDATES
                       ) -> Integer[Tensor, "N C S k"]:
    """Indices of the k projected vertices nearest each mask sample (no gradient; a k-d tree per view, on the CPU:
    2-3 times faster than a brute-force ``cdist`` + ``topk`` there)."""
    N, C, V, _ = uv.shape
    S = samples.shape[2]
    k = min(k, V)
    flat_uv = uv.detach().reshape(N * C, V, 2).double().cpu().numpy()
    flat_s = samples.reshape(N * C, S, 2).double().cpu().numpy()
    out = np.empty((N * C, S, k), np.int64)
    for v in range(N * C):  # views
        out[v] = cKDTree(flat_uv[v]).query(flat_s[v], k=k)[1].reshape(S, k)
    return torch.as_tensor(out, device=uv.device).reshape(N, C, S, k)


def vertex_face_table(faces: Integer[Tensor, "F 3"], num_verts: int
                      ) -> tuple[Integer[Tensor, "V D"], Integer[Tensor, "F1 3"]]:
    """(V, D) the faces around each vertex, padded with index F, and the faces (F + 1, 3) with a degenerate
    last face (0, 0, 0) the padding points at."""
    flat = faces.reshape(-1)
    counts = torch.bincount(flat, minlength=num_verts)
    order = torch.argsort(flat, stable=True)
    first = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(flat), device=faces.device) - first[flat[order]]
    table = torch.full((num_verts, int(counts.max())), len(faces), dtype=torch.long, device=faces.device)
    table[flat[order], rank] = order // 3
    padded = torch.cat([faces, torch.zeros(1, 3, dtype=faces.dtype, device=faces.device)])
    return table, padded


def covered_samples(uv: Float[Tensor, "N C V 2"], samples: Float[Tensor, "N C S 2"],
                    candidates: Integer[Tensor, "N C S k"], table: Integer[Tensor, "V D"],
                    faces: Integer[Tensor, "F1 3"], k: int = COVER_TEST) -> Bool[Tensor, "N C S"]:
    """Whether each mask sample lies inside a projected triangle around one of its ``k`` nearest vertices."""
    N, C, V, _ = uv.shape
    S = samples.shape[2]
    near = candidates[..., :k].reshape(N * C, S, -1)
    flat_uv, flat_s = uv.detach().reshape(N * C, V, 2), samples.reshape(N * C, S, 1, 2)
    out = torch.empty(N * C, S, dtype=torch.bool, device=uv.device)
    M = near.shape[2] * table.shape[1]
    with torch.no_grad():
        for v in _view_chunks(N * C, S * M * 6):
            corners = faces[table[near[v]].reshape(-1, S, M)]  # (views, S, M, 3) vertex indices
            tri = torch.gather(flat_uv[v], 1, corners.reshape(len(corners), -1, 1).expand(-1, -1, 2))
            a, b, c = tri.reshape(len(corners), S, M, 3, 2).unbind(3)
            p = flat_s[v]
            e = torch.stack([_cross(b - a, p - a), _cross(c - b, p - b), _cross(a - c, p - c)], dim=-1)
            area = _cross(b - a, c - a)
            inside = ((e >= 0).all(-1) | (e <= 0).all(-1)) & (area.abs() > 1e-9)
            out[v] = inside.any(-1)
    return out.reshape(N, C, S)


def _cross(u: Tensor, v: Tensor) -> Tensor:
    """z of the 2-D cross product of (..., 2) vectors."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _geman_mcclure(d2: Tensor, scale: float) -> Tensor:
    """Geman-McClure of squared distances ``d2``: ~d2 for small ones, saturating at ``scale^2``."""
    return d2 * scale ** 2 / (d2 + scale ** 2)


def silhouette_terms(verts: Float[Tensor, "N V 3"], targets: SilhouetteTargets, candidates: Integer[Tensor, "N C S k"],
                     uncovered: Float[Tensor, "N C S"], mm_per_px: Float[Tensor, "N C"], outside_margin_mm: float,
                     robust_mm: float) -> tuple[Float[Tensor, ""], Float[Tensor, ""]]:
    """The (outside, cover) terms: per view means of robust squared distances (cm^2), averaged over the views.

    Args:
        verts: posed vertices, world mm.
        targets: the prepared masks.
        candidates: :func:`nearest_candidates` of a recent step.
        uncovered: 1 for the mask samples outside the body's silhouette at a recent step (:func:`covered_samples`),
            0 for the others (they pull nothing).
        mm_per_px: size of a pixel at the body's depth in each view.
        outside_margin_mm: a vertex this far outside the mask costs nothing.
        robust_mm: Geman-McClure scale.
    """
    N, C = targets.view_weight.shape
    h, w = targets.dist.shape[-2:]
    uv, depth = project(verts, targets.proj)  # (N, C, V, 2), (N, C, V)
    scale = torch.tensor([2.0 / w, 2.0 / h], dtype=uv.dtype, device=uv.device)
    grid = (uv * scale - 1.0).reshape(N * C, 1, -1, 2)
    out_px = torch.nn.functional.grid_sample(targets.dist, grid, mode="bilinear", padding_mode="border",
                                             align_corners=False).reshape(N, C, -1)
    out_mm = (out_px * mm_per_px[..., None] - outside_margin_mm).clamp(min=0.0)
    front = (depth > _MIN_DEPTH_MM).to(uv.dtype)
    outside = (_geman_mcclure((out_mm / 10.0) ** 2, robust_mm / 10.0) * front).mean(-1)  # (N, C)
    S, k = candidates.shape[2:]
    near = torch.gather(uv, 2, candidates.reshape(N, C, S * k, 1).expand(-1, -1, -1, 2)).reshape(N, C, S, k, 2)
    gap_px = (near - targets.samples[:, :, :, None]).norm(dim=-1).min(dim=-1).values  # (N, C, S)
    gap_cm = gap_px * mm_per_px[..., None] / 10.0
    cover = (_geman_mcclure(gap_cm ** 2, robust_mm / 10.0) * uncovered).mean(-1)  # (N, C)
    views = targets.view_weight.sum(1).clamp(min=1.0)  # (N,)
    weight = targets.view_weight / views[:, None]
    return (outside * weight).sum(1).mean(), (cover * weight).sum(1).mean()


def mm_per_pixel(centres: Float[Tensor, "N 3"], targets: SilhouetteTargets) -> Float[Tensor, "N C"]:
    """(N, C) size of a pixel (mm) at the depth of each frame's body centre (world mm) in each camera."""
    depth = project(centres[:, None], targets.proj)[1][..., 0]  # (N, C)
    return depth.clamp(min=_MIN_DEPTH_MM) / targets.focal[None]


def rasterize_silhouettes(uv: Float[np.ndarray, "N C V 2"], depth: Float[np.ndarray, "N C V"],
                          faces: Integer[np.ndarray, "F 3"], size: tuple[int, int]) -> Bool[np.ndarray, "N C h w"]:
    """Silhouettes (h, w) = ``size`` of meshes projected to pixel coordinates ``uv`` (corner convention): the
    triangles filled at ``SUPERSAMPLE`` times the resolution (``cv2.fillConvexPoly``), pixels kept where at least
    half covered. Faces with a vertex behind the camera are skipped."""
    N, C = uv.shape[:2]
    h, w = size
    out = np.zeros((N, C, h, w), bool)
    # cv2 puts pixel centres on integers (the corner convention at +0.5); 4 fractional bits
    fixed = np.round((uv * SUPERSAMPLE - 0.5) * 16.0)
    fixed = np.clip(fixed, -(1 << 24), 1 << 24).astype(np.int32)
    image = np.zeros((h * SUPERSAMPLE, w * SUPERSAMPLE), np.uint8)
    for n in range(N):
        for c in range(C):
            keep = (depth[n, c][faces] > _MIN_DEPTH_MM).all(axis=1)
            image[:] = 0
            for tri in fixed[n, c][faces[keep]]:  # one triangle at a time: fillPoly would XOR overlaps
                cv2.fillConvexPoly(image, tri, 255, cv2.LINE_8, 4)
            out[n, c] = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA) >= 128
    return out


def silhouette_iou(rendered: Bool[np.ndarray, "N C h w"], masks: Bool[np.ndarray, "N C h w"]
                   ) -> Float64[np.ndarray, "N C"]:
    """(N, C) intersection over union per view; NaN where the mask is empty."""
    inter = (rendered & masks).sum(axis=(2, 3)).astype(np.float64)
    union = (rendered | masks).sum(axis=(2, 3)).astype(np.float64)
    iou = inter / np.maximum(union, 1.0)
    iou[~masks.any(axis=(2, 3))] = np.nan
    return iou
