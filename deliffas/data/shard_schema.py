"""The schema of a shard file (docs/shards.md, "Shard files"), checked against its manifest entry and meta.h5.

:func:`shard_problems` names every departure from the documented layout: a missing or extra dataset,
a wrong shape or dtype, ``window_rows`` outside the geometry block or pointing at other frames,
frames that differ from the manifest, cameras the conversion did not convert, a geometry block whose
vertex count or atlas side differs from ``meta.h5``. ``verify`` reports them; the dataset relies on them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from deliffas.data.shard_meta import SCHEMA_VERSION, ShardMeta

__all__ = ["shard_problems", "inside", "SHARD_FORMAT"]

SHARD_FORMAT = "deliffas-shard"

_IMAGE_KEYS = {"raw": ("rgba",), "png": ("png",), "jpeg": ("jpeg", "masks")}


def _dataset(f, key: str, problems: list[str], ndim: int, dtype) -> object | None:
    if key not in f:
        problems.append(f"dataset '{key}' missing")
        return None
    ds = f[key]
    if len(ds.shape) != ndim:
        problems.append(f"'{key}' has shape {ds.shape}, expected {ndim} dimensions")
        return None
    if dtype is not None and ds.dtype != np.dtype(dtype):
        problems.append(f"'{key}' has dtype {ds.dtype}, expected {np.dtype(dtype)}")
        return None
    return ds


def shard_problems(f, expected_frames: Sequence[int], meta: ShardMeta | None) -> list[str]:
    """Schema problems of an open shard ``f`` (h5py File), each one phrase; empty when it matches.

    Args:
        expected_frames: the shard's frames as the manifest lists them.
        meta: the conversion's ``meta.h5`` (vertex count, atlas side, converted cameras), or None.
    """
    problems: list[str] = []
    attrs = f.attrs
    if attrs.get("format") != SHARD_FORMAT or int(attrs.get("version", -1)) != SCHEMA_VERSION:
        return [f"not a {SHARD_FORMAT} file of version {SCHEMA_VERSION}"]
    if int(attrs.get("complete", 0)) != 1:
        problems.append("not marked complete")
    missing_attrs = [k for k in ("sequence", "codec", "window", "first_frame", "height", "width") if k not in attrs]
    if missing_attrs:
        return problems + [f"attributes {missing_attrs} missing"]
    T, H, W = int(attrs["window"]), int(attrs["height"]), int(attrs["width"])
    frames = _dataset(f, "frames", problems, 1, np.int64)
    cams = _dataset(f, "camera_ids", problems, 1, np.int64)
    rows = _dataset(f, "window_rows", problems, 2, np.int64)
    if frames is None or cams is None or rows is None:
        return problems
    frames, cams, rows = frames[()], cams[()], rows[()]
    N, C = len(frames), len(cams)
    if [int(x) for x in frames] != [int(x) for x in expected_frames]:
        problems.append(f"frames {frames.tolist()[:6]} differ from the manifest's {list(expected_frames)[:6]}")
    if meta is not None and not set(cams.tolist()) <= set(meta.converted_cameras.tolist()):
        problems.append(f"camera_ids {cams.tolist()} include cameras meta.h5 did not convert")
    if rows.shape != (N, T + 1):
        problems.append(f"'window_rows' has shape {rows.shape}, expected ({N}, {T + 1})")
    codec = str(attrs["codec"]).split(":")[0]
    keys = _IMAGE_KEYS.get(codec)
    if keys is None:
        problems.append(f"unknown codec {attrs['codec']!r}")
    else:
        shapes = {"rgba": (N, C, H, W, 4), "png": (N, C), "jpeg": (N, C), "masks": (N, C, H, W)}
        for key in keys:
            ds = _dataset(f, key, problems, len(shapes[key]), None)
            if ds is None:
                continue
            if ds.shape != shapes[key]:
                problems.append(f"'{key}' has shape {ds.shape}, expected {shapes[key]}")
            if key in ("rgba", "masks") and ds.dtype != np.uint8:
                problems.append(f"'{key}' has dtype {ds.dtype}, expected uint8")
    if "geometry" not in f:
        return problems + ["group 'geometry' missing"]
    g = f["geometry"]
    gframes = _dataset(g, "frames", problems, 1, np.int64)
    if gframes is None:
        return problems
    gframes = gframes[()]
    G = len(gframes)
    if rows.shape == (N, T + 1) and G:
        if rows.min(initial=0) < 0 or rows.max(initial=0) >= G:
            problems.append(f"'window_rows' points outside the {G} geometry rows")
        else:
            want = np.maximum(frames[:, None] - np.arange(T + 1)[None], int(attrs["first_frame"]))
            if not np.array_equal(gframes[rows], want):
                problems.append("'window_rows' points at geometry of other frames than f, f-1, ..., f-T")
    V = meta.rest_verts.shape[0] if meta is not None else None
    S = meta.atlas_res if meta is not None else None
    spec = {"dofs": (2, np.float64, None), "inner_verts": (3, np.float32, (V, 3)), "outer_verts": (3, np.float32, (V, 3)),
            "normal_maps_inner": (4, np.float16, (3, S, S)), "normal_maps_outer": (4, np.float16, (3, S, S))}
    for key, (ndim, dtype, tail) in spec.items():
        ds = _dataset(g, key, problems, ndim, dtype)
        if ds is None:
            continue
        if ds.shape[0] != G:
            problems.append(f"'geometry/{key}' has {ds.shape[0]} rows, geometry/frames {G}")
        if tail is not None and None not in tail and tuple(ds.shape[1:]) != tail:
            problems.append(f"'geometry/{key}' has shape {ds.shape}, expected ({G}, {', '.join(map(str, tail))})")
    return problems


def inside(root: Path, name: str) -> bool:
    """Whether ``root / name`` stays inside ``root`` (manifest names are relative paths, never ``..``)."""
    root = root.resolve()
    target = (root / name).resolve()
    return target == root or root in target.parents
