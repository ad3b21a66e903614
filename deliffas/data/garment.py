"""The synthetic loose garment: which vertices it covers, and how far it moves beyond the template.

A region (a DDC character's skirt label, or a lower-torso / upper-leg band of any body) gets smooth
per-vertex weights; :func:`garment_deformation` pushes it outward by a pose- and velocity-dependent
2-6 cm, which the skinned template cannot express (docs/data.md, synthetic captures).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from deliffas.io.formats.dynacap.character import Character
from deliffas.geometry.mesh_ops import vertex_normals

__all__ = ["GARMENT_LABEL", "garment_weights", "ddc_garment_region", "smpl_garment_region", "region_weights",
           "GarmentFrames", "garment_deformation"]

GARMENT_LABEL = 12
"""Segmentation label of the loose garment (skirt) of the procedural character."""
_BAND = (0.30, 0.57)
"""Fallback garment region: rest-pose height band (fraction of the mesh height) for bodies without label 12."""
_NOT_GARMENT_BONES = ("Arm", "Hand", "Shoulder", "Head", "Neck")
_SMPL_FIRST_NOT_GARMENT_JOINT = 12
"""SMPL joints 12-23 (neck, collars, head, shoulders, elbows, wrists, hands) never carry the garment."""


def _vertex_smoother(faces: np.ndarray, num_verts: int):
    """(V, V) sparse row-stochastic matrix: x <- mean of x over the vertex and its neighbours."""
    f = np.asarray(faces, np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0], np.arange(num_verts)])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2], np.arange(num_verts)])
    A = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(num_verts, num_verts))
    A.data[:] = 1.0  # duplicate edges count once
    deg = np.asarray(A.sum(axis=1)).ravel()
    return sp.diags(1.0 / np.maximum(deg, 1)) @ A


def _smooth(values: np.ndarray, smoother, iterations: int) -> np.ndarray:
    """Apply the smoother to (V,) or (V, K) or (N, V, K) values ``iterations`` times."""
    x = values
    for _ in range(iterations):
        if x.ndim == 3:
            n, v, k = x.shape
            x = (smoother @ x.transpose(1, 0, 2).reshape(v, n * k)).reshape(v, n, k).transpose(1, 0, 2)
        else:
            x = smoother @ x
    return np.asarray(x)


def garment_weights(character: Character, smooth_iterations: int = 4) -> np.ndarray:
    """Per-vertex garment weight in [0, 1] of a DDC character (:func:`ddc_garment_region`, smoothed)."""
    return region_weights(ddc_garment_region(character), character.mesh.faces, smooth_iterations)


def ddc_garment_region(character: Character) -> np.ndarray:
    """(V,) bool loose region of a DDC character.

    The region is segmentation label ``GARMENT_LABEL`` (12, the procedural character's skirt); for
    characters without it (e.g. the DDC sample), the rest-pose height band ``_BAND`` of the mesh
    (lower torso and upper legs) minus vertices dominated by arm, hand, head or neck bones.
    """
    mesh = character.mesh
    seg = character.segmentation
    if seg is not None and np.any(seg == GARMENT_LABEL):
        return seg == GARMENT_LABEL
    core = _height_band(mesh.verts[:, 1])
    skin = character.skin
    dominant = skin.indices[np.arange(skin.num_verts), np.argmax(skin.weights, axis=1)]
    bad = np.array([any(k in b for k in _NOT_GARMENT_BONES) for b in skin.bones])
    return core & ~bad[dominant]


def smpl_garment_region(rest_verts: np.ndarray, lbs_weights: np.ndarray) -> np.ndarray:
    """(V,) bool loose region of an SMPL body: the rest-pose height band ``_BAND`` (lower torso and upper
    legs) minus vertices whose dominant joint is an arm, hand, neck or head joint (SMPL joints 12-23)."""
    dominant = np.argmax(np.asarray(lbs_weights), axis=1)
    return _height_band(np.asarray(rest_verts)[:, 1]) & (dominant < _SMPL_FIRST_NOT_GARMENT_JOINT)


def _height_band(y: np.ndarray) -> np.ndarray:
    lo, hi = y.min(), y.max()
    h = (y - lo) / max(hi - lo, 1e-9)
    return (h >= _BAND[0]) & (h <= _BAND[1])


def region_weights(core: np.ndarray, faces: np.ndarray, smooth_iterations: int = 4) -> np.ndarray:
    """Per-vertex garment weight in [0, 1]: 1 on the region ``core`` (V,) bool, fading over a few rings outside it."""
    core = np.asarray(core, bool)
    smoother = _vertex_smoother(faces, len(core))
    w = _smooth(core.astype(np.float64), smoother, smooth_iterations)
    return np.maximum(w / max(w.max(), 1e-12), core.astype(np.float64)).clip(0.0, 1.0)


@dataclass(frozen=True)
class GarmentFrames:
    """The garment model of one sequence.

    Attributes:
        offsets: (N, V, 3) float64 mm, ground truth minus skinned template.
        albedo_scale: (N, V) float64 wrinkle-band multiplier of the albedo.
        spread_mm: (N,) leg spread of the region relative to the rest pose (the pose input).
        speed_mm_s: (N,) mean lagged speed of the region (the velocity input).
    """
    offsets: np.ndarray
    albedo_scale: np.ndarray
    spread_mm: np.ndarray
    speed_mm_s: np.ndarray


def garment_deformation(posed: np.ndarray, faces: np.ndarray, rest_verts: np.ndarray, weights: np.ndarray,
                        fps: float = 25.0, min_mm: float = 20.0, max_mm: float = 60.0,
                        lag: float = 0.7) -> GarmentFrames:
    """Pose- and velocity-dependent outward displacement of the garment region (beyond the template).

    Per vertex i and frame f (w_i the garment weight, h_i in [0, 1] from the waist to the hem in the
    rest pose):

        d_if = w_i * smooth(clip(min + 14 h_i + pose_f + vel_if, min, max))  [mm]
        pose_f = 15 * clip(spread_f / 80, -0.5, 1)                   (leg spread vs. rest, mm)
        vel_if = 20 * clip(|u_if| / 1000, 0, 1) * (0.4 + 0.6 * trailing_if)

    where u is the template's vertex velocity (mm/s) low-passed over time (``lag``) and over the
    surface, and trailing = max(0, -dir . u/|u|) (cloth lags behind the motion). The direction is the
    vertex normal blended with the horizontal radial direction from the region's centre (a flare);
    smooth() averages over 3 rings of the surface before the (smooth) weight is applied.

    Args:
        posed: (N, V, 3) skinned template vertices of consecutive frames, mm.
        faces: (F, 3).
        rest_verts: (V, 3) template in its rest pose.
        weights: (V,) garment weights from ``garment_weights``.
    """
    num_frames, num_verts = posed.shape[:2]
    smoother = _vertex_smoother(faces, num_verts)
    w = np.asarray(weights, np.float64)
    core = w > 0.5
    y = rest_verts[:, 1]
    y_top, y_bot = y[core].max(), y[core].min()
    hem = np.clip((y_top - y) / max(y_top - y_bot, 1e-9), 0.0, 1.0)
    wn = w / w.sum()
    normals = vertex_normals(posed, faces)  # (N, V, 3)
    centre = np.einsum("v,nvc->nc", wn, posed)  # (N, 3)
    radial = posed - centre[:, None]
    radial[..., 1] = 0.0
    radial /= np.maximum(np.linalg.norm(radial, axis=-1, keepdims=True), 1e-9)
    direction = normals + radial
    direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-9)
    lower = core & (hem > 0.5)

    def spread(v: np.ndarray) -> np.ndarray | float:  # (..., V, 3) -> (...) RMS horizontal radius of the lower region
        c = v[..., lower, :].mean(axis=-2, keepdims=True)
        d = v[..., lower, :] - c
        return np.sqrt((d[..., 0] ** 2 + d[..., 2] ** 2).mean(axis=-1))

    spread_mm = spread(posed) - spread(rest_verts)
    pose_term = 15.0 * np.clip(spread_mm / 80.0, -0.5, 1.0)  # (N,)
    vel = np.diff(posed, axis=0, prepend=posed[:1]) * fps  # (N, V, 3) mm/s
    lagged = np.empty_like(vel)
    acc = np.zeros_like(vel[0])
    for f in range(num_frames):  # a recursion over time (frames), vectorised over vertices
        acc = lag * acc + (1.0 - lag) * vel[f]
        lagged[f] = acc
    lagged = _smooth(lagged, smoother, 3)
    speed = np.linalg.norm(lagged, axis=-1)  # (N, V)
    trailing = np.clip(-np.einsum("nvc,nvc->nv", direction, lagged) / np.maximum(speed, 1e-9), 0.0, 1.0)
    vel_term = 20.0 * np.clip(speed / 1000.0, 0.0, 1.0) * (0.4 + 0.6 * trailing)
    mag = np.clip(min_mm + 14.0 * hem[None] + pose_term[:, None] + vel_term, min_mm, max_mm)
    mag = _smooth(mag.T, smoother, 3).T * w[None]  # (N, V); exactly 0 where w = 0
    offsets = mag[..., None] * direction
    phase = 2 * np.pi * spread_mm / 120.0
    bands = 0.5 + 0.5 * np.cos(2 * np.pi * 4.0 * hem[None] + phase[:, None])
    albedo_scale = 1.0 - 0.22 * w[None] * bands
    speed_mean = (speed * wn[None]).sum(axis=1)
    return GarmentFrames(offsets, albedo_scale, spread_mm, speed_mean)
