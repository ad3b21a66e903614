"""Ground-truth renderer of the synthetic captures: ray-cast textured, Blinn-Phong shaded RGBA views.

Per pixel (col, row) one ray through (col + 0.5, row + 0.5) (``Camera.rays``, docs/conventions.md),
or s x s rays at ((col + (i + 0.5) / s), …) with ``supersample = s``. A hit takes the template's
per-corner uv (barycentric interpolation), the texture bilinearly through
``deliffas.geometry.sampling.sample_uv``, the interpolated vertex normal of the *rendered* surface, and
is shaded by

    rgb = albedo * albedo_scale * (ambient * ao + diffuse * max(0, n.l)) + specular * ao * max(0, n.h)^shininess

with l the fixed direction towards the light, h = normalize(l + v), v the direction to the camera:
the specular term is view-dependent, ``ao`` (ambient occlusion of the posed geometry) and
``albedo_scale`` (e.g. wrinkle bands) are pose-dependent per-vertex inputs. Alpha is the covered
fraction of the pixel's rays; RGB is straight (not premultiplied) colour: the mean colour of the rays
that hit the surface where alpha > 0, ``background`` where no ray hits. As for a real capture's
photograph and mask, ``image * alpha + background * (1 - alpha)`` is what a camera integrating over
the pixel sees in front of ``background`` (``engine.samples.composite_target``, black background).

open3d is reached through ``deliffas.geometry.raycast`` (its one door).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from deliffas.checks import check_shape
from deliffas.data.synth_config import ShadingConfig
from deliffas.io.cameras import Camera, pixel_centers
from deliffas.geometry import raycast
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.sampling import sample_uv

__all__ = ["ShadingConfig", "RenderedView", "render_views", "camera_rays", "vertex_ambient_occlusion",
           "fibonacci_hemisphere"]


@dataclass(frozen=True)
class RenderedView:
    """One rendered camera view.

    Attributes:
        rgb: (H, W, 3) uint8, straight colour: the mean over the pixel's rays that hit the surface
            where ``alpha > 0``, the background where none hits.
        alpha: (H, W) uint8, coverage (255 = every ray of the pixel hit the surface).
    """
    rgb: np.ndarray
    alpha: np.ndarray


def fibonacci_hemisphere(num: int) -> np.ndarray:
    """(num, 3) float64 unit directions spread over the +z hemisphere, cosine-weighted (deterministic)."""
    i = np.arange(num) + 0.5
    r = np.sqrt(i / num)  # cosine-weighted: uniform on the disk, lifted to the hemisphere
    phi = np.pi * (1 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - r**2)], axis=1)


def vertex_ambient_occlusion(verts: np.ndarray, faces: np.ndarray, normals: np.ndarray, num_dirs: int = 16,
                             max_dist: float = 250.0, seed: int = 0) -> np.ndarray:
    """Ambient-occlusion proxy of a posed mesh: fraction of unoccluded hemisphere rays per vertex.

    Args:
        verts: (V, 3) float, mm.
        faces: (F, 3) int.
        normals: (V, 3) unit vertex normals.
        num_dirs: rays per vertex (a fixed cosine-weighted set, rotated per vertex by a seeded angle).
        max_dist: mm; hits farther than this do not occlude.
        seed: seeds the per-vertex rotation about the normal.

    Returns:
        (V,) float32 in [0, 1], 1 = nothing within ``max_dist``.
    """
    check_shape("verts", verts, "V 3")
    check_shape("normals", normals, "V 3", {"V": len(verts)})
    num_verts = len(verts)
    local = fibonacci_hemisphere(num_dirs)  # (K, 3)
    angle = np.random.default_rng(seed).uniform(0, 2 * np.pi, num_verts)
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(n[:, 1:2]) < 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
    t1 = np.cross(helper, n)
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    t2 = np.cross(n, t1)
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    a1, a2 = c * t1 + s * t2, -s * t1 + c * t2  # rotated tangent frame
    dirs = (local[None, :, 0:1] * a1[:, None] + local[None, :, 1:2] * a2[:, None]
            + local[None, :, 2:3] * n[:, None])  # (V, K, 3)
    origins = np.broadcast_to((verts + 0.5 * n)[:, None], dirs.shape)  # 0.5 mm off the surface
    scene = raycast.build_scene(verts, faces)
    t, _, _ = raycast.first_hits(scene, origins.reshape(-1, 3), dirs.reshape(-1, 3))
    occluded = (t.reshape(num_verts, num_dirs) < max_dist)
    return (1.0 - occluded.mean(axis=1)).astype(np.float32)


def camera_rays(camera: Camera, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rays of s x s samples per pixel (s = ``supersample``), ordered (H, W, s*s).

    Sample (i, j) of pixel (col, row) goes through (col + (j + 0.5) / s, row + (i + 0.5) / s); s = 1
    is ``Camera.rays()`` (pixel centres). Reuse the result for every frame of a static camera.

    Returns:
        origins (H*W*s*s, 3) float32 mm, directions (H*W*s*s, 3) float32 unit.
    """
    s = max(1, int(supersample))
    if s == 1:
        o, d = camera.rays()
    else:
        corners = pixel_centers(camera.width, camera.height) - 0.5  # (H, W, 2)
        offs = (np.arange(s) + 0.5) / s
        oc, orow = np.meshgrid(offs, offs)
        sub = np.stack([oc.ravel(), orow.ravel()], axis=1)  # (s*s, 2)
        o, d = camera.rays((corners[:, :, None, :] + sub[None, None]).reshape(-1, 2))
    return o.astype(np.float32), d.astype(np.float32)


def render_views(verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, face_uvs: np.ndarray, texture: np.ndarray,
                 cameras: Sequence[Camera], vertex_ao: np.ndarray | None = None,
                 albedo_scale: np.ndarray | None = None, shading: ShadingConfig = ShadingConfig(),
                 normals: np.ndarray | None = None,
                 rays: Sequence[tuple[np.ndarray, np.ndarray]] | None = None) -> list[RenderedView]:
    """Render one posed surface into every camera.

    Args:
        verts: (V, 3) float, mm, world frame (the ground-truth surface).
        faces: (F, 3) int.
        uvs: (T, 2) float, per-corner uv table (v up).
        face_uvs: (F, 3) int into ``uvs``.
        texture: (Ht, Wt, 3) float32 in [0, 1], row 0 = top (v = 1).
        cameras: the views to render (each at its own size).
        vertex_ao: (V,) float in [0, 1] or None (= 1).
        albedo_scale: (V,) float multiplier of the albedo, or None (= 1).
        shading: light and material.
        normals: (V, 3) unit vertex normals of ``verts`` (computed when None).
        rays: per camera ``camera_rays(camera, shading.supersample)``, to reuse across frames.

    Returns:
        One ``RenderedView`` per camera.
    """
    sizes = check_shape("verts", verts, "V 3")
    check_shape("faces", faces, "F 3")
    check_shape("face_uvs", face_uvs, "F 3", {"F": len(faces)})
    check_shape("texture", texture, "_ _ 3")
    faces = np.asarray(faces, dtype=np.int64)
    f32 = np.float32  # shading in float32: 8-bit output, half the memory traffic
    vn = (vertex_normals(np.asarray(verts, np.float64), faces) if normals is None else np.asarray(normals)).astype(f32)
    ao = np.ones(sizes["V"], f32) if vertex_ao is None else np.asarray(vertex_ao, f32)
    scale = np.ones(sizes["V"], f32) if albedo_scale is None else np.asarray(albedo_scale, f32)
    corner_uv = np.asarray(uvs, f32)[np.asarray(face_uvs, np.int64)]  # (F, 3, 2)
    tex = torch.from_numpy(np.ascontiguousarray(np.asarray(texture, np.float32).transpose(2, 0, 1)))[None]
    light = np.asarray(shading.light_dir, f32)
    light /= np.linalg.norm(light)
    bg = np.asarray(shading.background, f32)
    s = max(1, int(shading.supersample))
    scene = raycast.build_scene(verts, faces)
    out = []
    for k, cam in enumerate(cameras):  # a handful of cameras; every pixel is vectorised
        origins, dirs = rays[k] if rays is not None else camera_rays(cam, s)
        t, face, bary = raycast.first_hits(scene, origins, dirs)
        hit = face >= 0
        fh, bh, dh = face[hit], bary[hit], dirs[hit].astype(f32)
        fv = faces[fh]  # (M, 3)
        uv = np.einsum("mk,mkc->mc", bh, corner_uv[fh])  # (M, 2)
        albedo = sample_uv(tex, torch.zeros(len(uv), dtype=torch.long), torch.from_numpy(uv))
        albedo = albedo.numpy() * np.einsum("mk,mk->m", bh, scale[fv])[:, None]
        n = np.einsum("mk,mkc->mc", bh, vn[fv])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        view = -dh
        n = np.where((np.einsum("mc,mc->m", n, view) < 0)[:, None], -n, n)  # back faces shade as front faces
        occl = np.einsum("mk,mk->m", bh, ao[fv])
        ndl = np.clip(n @ light, 0.0, None)
        half = light[None] + view
        half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
        spec = np.where(ndl > 0, np.clip(np.einsum("mc,mc->m", n, half), 0.0, None) ** f32(shading.shininess), f32(0.0))
        color = albedo * (shading.ambient * occl + shading.diffuse * ndl)[:, None]
        color += (shading.specular * occl * spec)[:, None]
        color = np.clip(color, f32(0.0), f32(1.0))
        acc = np.zeros((len(face), 3), f32)
        acc[hit] = color
        acc = acc.reshape(cam.height, cam.width, s * s, 3).sum(axis=2)
        hits = hit.reshape(cam.height, cam.width, s * s).sum(axis=2)
        cover = hits / (s * s)
        # straight colour: the hits' mean (not premultiplied by coverage); the background where none hits
        rgb = np.where((hits > 0)[..., None], acc / np.maximum(hits, 1)[..., None], bg)
        out.append(RenderedView(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8),
                                np.round(cover * 255).astype(np.uint8)))
    return out
