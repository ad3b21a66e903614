"""UV atlases with per-corner UVs and their texel -> (face, barycentrics) tables.

Conventions (docs/conventions.md, binding): uv in [0, 1]^2 with v up (OBJ); per-corner UVs
``face_uvs (F, 3)`` index ``uvs (T, 2)``; vertices are never split at seams. Texel (row i, col j)
of an atlas image of side S has its centre at u = (j + 0.5) / S, v = 1 - (i + 0.5) / S; row 0 is
the top (v = 1).

The texel table is computed once per atlas and resolution; per-frame normal maps are then a
gather through it (``deliffas.geometry.normal_maps``).

Arrays: the atlas and its tables are numpy records. ``UVAtlas`` takes numpy arrays or torch
tensors and stores read-only numpy copies (the one conversion); everything here returns numpy.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from jaxtyping import Bool, Float, Integer, Real

from deliffas.checks import check_shape
from deliffas.optional import import_optional
from deliffas.geometry.arrays import ArrayLike, to_numpy

__all__ = [
    "UVAtlas",
    "TexelTable",
    "uv_texel_table",
    "texel_centers_uv",
    "GUTTER_BARY_MIN",
    "UV_AREA_EPS",
]

log = logging.getLogger(__name__)

GUTTER_BARY_MIN = -0.5
"""Extrapolated barycentrics of gutter texels are clamped from below at this value and then
rescaled to sum to 1 (see ``uv_texel_table``). The point stays on the face's plane and within the
face scaled about its centroid (every weight in [-0.5, 2])."""

UV_AREA_EPS = 1e-12
"""A UV face with |2 x signed area| <= this, in texel^2 units, is zero-area: it covers nothing."""

_INSIDE_TOL = 1e-9  # a texel centre on a face edge counts as inside (barycentric >= -tol)
_CHUNK_CANDIDATES = 2_000_000  # candidate (face, texel) pairs processed at once


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class UVAtlas:
    """Per-corner UV coordinates of a mesh (the mesh's vertex order is untouched).

    Attributes:
        uvs: (T, 2) float64, uv in [0, 1]^2, v up.
        face_uvs: (F, 3) int64, face_uvs[f, k] indexes the uv of corner k of face f.
    """

    uvs: Float[ArrayLike, "T 2"]
    face_uvs: Integer[ArrayLike, "F 3"]

    def __post_init__(self) -> None:
        sizes = check_shape("uvs", self.uvs, "T 2")
        check_shape("face_uvs", self.face_uvs, "F 3")
        fu = to_numpy(self.face_uvs)
        if fu.size and (fu.min() < 0 or fu.max() >= sizes["T"]):
            raise ValueError(f"face_uvs: indices must be in [0, {sizes['T']}), got [{fu.min()}, {fu.max()}]")
        object.__setattr__(self, "uvs", _readonly(to_numpy(self.uvs, np.float64)))
        object.__setattr__(self, "face_uvs", _readonly(to_numpy(self.face_uvs, np.int64)))

    @property
    def num_faces(self) -> int:
        return int(self.face_uvs.shape[0])

    @property
    def corner_uvs(self) -> Float[np.ndarray, "F 3 2"]:
        """(F, 3, 2) float64 uv of every face corner."""
        return self.uvs[self.face_uvs]

    @classmethod
    def from_mesh(
        cls,
        verts: Real[ArrayLike, "V 3"] | None,
        faces: Integer[ArrayLike, "F 3"],
        uvs: Float[ArrayLike, "T 2"] | None = None,
        face_uvs: Integer[ArrayLike, "F 3"] | None = None,
        *,
        resolution: int = 1024,
        padding: int = 4,
    ) -> "UVAtlas":
        """The template's own UVs when given, otherwise a new xatlas parametrisation.

        Args:
            verts: (V, 3) float, mm (only used by xatlas).
            faces: (F, 3) int, 0-based.
            uvs: (T, 2) float or None.
            face_uvs: (F, 3) int or None (both or neither).
            resolution: xatlas packing resolution (texels); only for a new parametrisation.
            padding: xatlas padding between charts, texels; only for a new parametrisation.

        Returns:
            UVAtlas whose ``face_uvs`` row f belongs to ``faces`` row f. xatlas splits vertices at
            seams; its ``vmapping`` is checked to map the split vertices back to exactly the
            original corners, so the result is per-corner uvs on the original vertex indices.
            xatlas's uvs are rescaled by (width, height) / max(width, height) so texels are square.
        """
        check_shape("faces", faces, "F 3")
        faces = to_numpy(faces, np.int64)
        if (uvs is None) != (face_uvs is None):
            raise ValueError("UVAtlas.from_mesh: give both uvs and face_uvs, or neither")
        if uvs is not None:
            check_shape("face_uvs", face_uvs, "F 3", {"F": len(faces)})
            return cls(uvs, face_uvs)
        check_shape("verts", verts, "V 3")
        xatlas = import_optional("xatlas", "UVAtlas.from_mesh without uvs needs the 'xatlas' package")
        atlas = xatlas.Atlas()
        atlas.add_mesh(np.ascontiguousarray(to_numpy(verts), dtype=np.float32), np.ascontiguousarray(faces, dtype=np.uint32))
        pack = xatlas.PackOptions()
        pack.resolution = int(resolution)
        pack.padding = int(padding)
        atlas.generate(pack_options=pack)
        vmapping, indices, xuvs = atlas[0]
        indices = indices.astype(np.int64)
        if indices.shape != faces.shape or not np.array_equal(vmapping.astype(np.int64)[indices], faces):
            raise RuntimeError(
                f"xatlas changed the face list (got indices {indices.shape} for faces {faces.shape}) "
                "or its vmapping does not reproduce the input corners"
            )
        w, h = float(atlas.width), float(atlas.height)
        scale = np.array([w, h]) / max(w, h, 1.0)
        return cls(xuvs.astype(np.float64) * scale, indices)


@dataclass(frozen=True)
class TexelTable:
    """Which face and barycentrics each texel of an S x S atlas image samples.

    Attributes:
        face: (S, S) int64, face index per texel, -1 where not ``valid``.
        bary: (S, S, 3) float32, barycentrics of the texel centre's uv in that face (sum 1);
            exact and in [0, 1] on covered texels, extrapolated and clamped on gutter texels,
            0 where not ``valid``.
        covered: (S, S) bool, texel centre inside a UV face (before gutter dilation).
        valid: (S, S) bool, covered or filled by the gutter dilation.
        degenerate_faces: (K,) int64, faces with zero UV area (they cover no texel).
    """

    face: Integer[np.ndarray, "S S"]
    bary: Float[np.ndarray, "S S 3"]
    covered: Bool[np.ndarray, "S S"]
    valid: Bool[np.ndarray, "S S"]
    degenerate_faces: Integer[np.ndarray, "K"] = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def size(self) -> int:
        """S, the atlas side in texels."""
        return int(self.face.shape[0])


def texel_centers_uv(size: int) -> Float[np.ndarray, "S S 2"]:
    """uv of every texel centre of an S x S atlas image.

    Returns:
        (S, S, 2) float64, [i, j] = ((j + 0.5) / S, 1 - (i + 0.5) / S).
    """
    c = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(c, 1.0 - c)  # u varies along columns, v along rows
    return np.stack([u, v], axis=-1)


def _face_frames(corner_uvs: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Corner positions in texel-index space (x = col, y = row) and the barycentric frame.

    Returns:
        p0 (F, 2), e1 (F, 2), e2 (F, 2), det (F,) with det = cross(e1, e2).
    """
    x = corner_uvs[..., 0] * size - 0.5  # texel col j has its centre at x = j
    y = (1.0 - corner_uvs[..., 1]) * size - 0.5  # texel row i has its centre at y = i
    p = np.stack([x, y], axis=-1)  # (F, 3, 2)
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    return p[:, 0], e1, e2, det


def _bary(px: np.ndarray, py: np.ndarray, p0: np.ndarray, e1: np.ndarray, e2: np.ndarray, det: np.ndarray) -> np.ndarray:
    """Barycentrics (N, 3) of points (px, py) (N,) in faces given row-wise (p0, e1, e2, det)."""
    dx = px - p0[:, 0]
    dy = py - p0[:, 1]
    b1 = (dx * e2[:, 1] - dy * e2[:, 0]) / det
    b2 = (e1[:, 0] * dy - e1[:, 1] * dx) / det
    return np.stack([1.0 - b1 - b2, b1, b2], axis=-1)


def _clamp_extrapolated(b: np.ndarray) -> np.ndarray:
    """Clamp affine barycentrics from below at GUTTER_BARY_MIN and rescale to sum 1."""
    b = np.maximum(b, GUTTER_BARY_MIN)
    return b / b.sum(axis=-1, keepdims=True)  # sum >= 1 after raising negatives


def _covering_candidates(p0: np.ndarray, e1: np.ndarray, e2: np.ndarray, det: np.ndarray, lo: np.ndarray,
                         extent: np.ndarray, counts: np.ndarray, S: int) -> tuple[list, list, list, list]:
    """Every (texel, face) pair whose texel centre a face covers, from each face's bounding-box candidates in
    chunks of ``_CHUNK_CANDIDATES``: lists of flat texel ids, face ids, smallest barycentrics and barycentrics."""
    texel_hits, face_hits, score_hits, bary_hits = [], [], [], []
    cum = np.cumsum(counts)
    start_face, num_faces = 0, len(det)
    while start_face < num_faces:
        base = cum[start_face - 1] if start_face else 0
        stop_face = int(np.searchsorted(cum, base + _CHUNK_CANDIDATES, side="right"))
        stop_face = max(stop_face, start_face + 1)
        fids = np.arange(start_face, stop_face)
        c = counts[fids]
        total = int(c.sum())
        if total:
            fid = np.repeat(fids, c)  # (N,)
            offsets = np.repeat(np.cumsum(c) - c, c)
            k = np.arange(total) - offsets
            w = extent[fid, 0]
            col = lo[fid, 0] + k % w
            row = lo[fid, 1] + k // w
            b = _bary(col.astype(np.float64), row.astype(np.float64), p0[fid], e1[fid], e2[fid], det[fid])
            bmin = b.min(axis=1)
            ok = bmin >= -_INSIDE_TOL
            texel_hits.append(row[ok] * S + col[ok])
            face_hits.append(fid[ok])
            score_hits.append(bmin[ok])
            bary_hits.append(b[ok])
        start_face = stop_face
    return texel_hits, face_hits, score_hits, bary_hits


def _fill_gutter(face: np.ndarray, bary: np.ndarray, valid: np.ndarray, covered: np.ndarray, S: int, gutter: int,
                 frames: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> None:
    """Give the empty texels within ``gutter`` rings of the covered set the face of their nearest covered texel
    with extrapolated barycentrics (in place: ``face`` (S*S,), ``bary`` (S*S, 3), ``valid`` (S*S,))."""
    from scipy import ndimage  # scipy only where a gutter is grown

    p0, e1, e2, det = frames
    cov2 = covered.reshape(S, S)
    grown = ndimage.binary_dilation(cov2, structure=np.ones((3, 3), bool), iterations=gutter)
    fill = (grown & ~cov2).reshape(-1)
    _, (near_r, near_c) = ndimage.distance_transform_edt(~cov2, return_indices=True)
    fill_idx = np.flatnonzero(fill)
    src = near_r.reshape(-1)[fill_idx] * S + near_c.reshape(-1)[fill_idx]
    fface = face[src]
    rows, cols = np.divmod(fill_idx, S)
    b = _bary(cols.astype(np.float64), rows.astype(np.float64), p0[fface], e1[fface], e2[fface], det[fface])
    face[fill_idx] = fface
    bary[fill_idx] = _clamp_extrapolated(b)
    valid[fill_idx] = True


def uv_texel_table(atlas: UVAtlas, size: int, gutter: int = 2) -> TexelTable:
    """Rasterise the atlas in UV space at texel centres, then dilate by ``gutter`` rings.

    Coverage: a texel is covered by a face when its centre's barycentrics are all >= -1e-9.
    A centre covered by several faces (shared edges, overlapping charts) takes the face whose
    smallest barycentric is largest (ties: lowest face index). Work is vectorised over the
    (face, texel) candidates of each face's bounding box, in chunks.

    Gutter: empty texels within ``gutter`` rings (8-neighbourhood dilation) of the covered set take
    the face of their nearest covered texel (Euclidean, ``scipy.ndimage.distance_transform_edt``)
    with barycentrics *extrapolated* for their own centre, so bilinear lookups across chart
    borders read a continuation of the chart. Extrapolated weights are clamped from below at
    ``GUTTER_BARY_MIN`` and rescaled to sum 1, which keeps the point on the face's plane (an
    affine combination) and bounded even for sliver faces.

    Zero-area UV faces cover nothing; their count is logged as a warning and their ids stored in
    ``degenerate_faces``.

    Args:
        atlas: the per-corner uvs.
        size: S, the atlas side in texels.
        gutter: number of dilation rings (0 disables).

    Returns:
        TexelTable of side S.
    """
    if size <= 0:
        raise ValueError(f"uv_texel_table: size must be positive, got {size}")
    if gutter < 0:
        raise ValueError(f"uv_texel_table: gutter must be >= 0, got {gutter}")
    S = int(size)
    p0, e1, e2, det = _face_frames(atlas.corner_uvs, S)
    degenerate = np.abs(det) <= UV_AREA_EPS
    degenerate_ids = np.flatnonzero(degenerate).astype(np.int64)
    if len(degenerate_ids):
        log.warning("uv_texel_table: %d zero-area UV faces cover no texel (first face ids %s)", len(degenerate_ids),
                    degenerate_ids[:10].tolist())

    corners = p0[:, None, :] + np.stack([np.zeros_like(e1), e1, e2], axis=1)  # (F, 3, 2)
    lo = np.ceil(corners.min(axis=1) - _INSIDE_TOL).astype(np.int64)  # (F, 2) (x, y)
    hi = np.floor(corners.max(axis=1) + _INSIDE_TOL).astype(np.int64)
    lo = np.clip(lo, 0, S - 1)
    hi = np.clip(hi, -1, S - 1)
    extent = np.maximum(hi - lo + 1, 0)  # (F, 2) columns, rows
    inside_image = (corners.max(axis=1) >= -0.5).all(1) & (corners.min(axis=1) <= S - 0.5).all(1)
    counts = np.where(degenerate | ~inside_image, 0, extent[:, 0] * extent[:, 1])  # (F,)

    texel_hits, face_hits, score_hits, bary_hits = _covering_candidates(p0, e1, e2, det, lo, extent, counts, S)
    face = np.full(S * S, -1, np.int64)
    bary = np.zeros((S * S, 3), np.float64)
    if texel_hits:
        texel_all = np.concatenate(texel_hits)
        face_all = np.concatenate(face_hits)
        score_all = np.concatenate(score_hits)
        bary_all = np.concatenate(bary_hits)
        # best candidate per texel: largest min-barycentric, then lowest face index
        order = np.lexsort((face_all, -score_all, texel_all))
        texel_sorted = texel_all[order]
        first = np.ones(len(order), bool)
        first[1:] = texel_sorted[1:] != texel_sorted[:-1]
        pick = order[first]
        face[texel_all[pick]] = face_all[pick]
        bary[texel_all[pick]] = np.clip(bary_all[pick], 0.0, 1.0)
        bary[texel_all[pick]] /= bary[texel_all[pick]].sum(axis=1, keepdims=True)
    covered = face >= 0

    valid = covered.copy()
    if gutter > 0 and covered.any() and not covered.all():
        _fill_gutter(face, bary, valid, covered, S, gutter, (p0, e1, e2, det))

    return TexelTable(
        face=face.reshape(S, S),
        bary=bary.reshape(S, S, 3).astype(np.float32),
        covered=covered.reshape(S, S),
        valid=valid.reshape(S, S),
        degenerate_faces=degenerate_ids,
    )
