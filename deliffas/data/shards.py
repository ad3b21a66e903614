"""Sharded HDF5 storage of converted captures: shard/meta writers and readers, manifest, checksums, verify.

An output folder (schema in docs/shards.md) holds

- ``meta.h5``: cameras, split, the character (faces, uvs, texel table) and conversion settings;
- ``shards/<sequence>-<k:05d>.h5``: per shard a run of frames with their images/masks for the
  converted cameras and the geometry (DOFs, inner/outer vertices, normal maps) of those frames and of
  their temporal-window predecessors, so every shard is self-contained;
- ``manifest.json``: the plan and the *complete* shards with their sha256, rewritten atomically after
  every finished shard (readers see finished shards while a conversion continues) and finally with
  ``"complete": true``. It holds no timestamps: two conversions of the same input are identical.

Every file is written under a temporary name and renamed when complete, so a file under its final
name is always whole. ``ShardSet`` reads only what the manifest lists.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
from jaxtyping import Float, Integer

from deliffas.checks import finite_as
from deliffas.io.infra.files import durable_replace, sha256_file, temp_path
from deliffas.data.shard_meta import SCHEMA_VERSION, ShardMeta, read_meta
from deliffas.data.shard_schema import SHARD_FORMAT, inside, shard_problems
from deliffas.data.verify_config import ShardVerification, VerifyConfig

__all__ = [
    "open_shard_set",
    "VerifyConfig",
    "verify_conversion",
    "ShardVerification",
    "ShardReadError",
    "SCHEMA_VERSION",
    "MANIFEST_NAME",
    "META_NAME",
    "SHARD_DIR",
    "Codec",
    "ShardGeometry",
    "ShardWriter",
    "ShardFile",
    "ShardInfo",
    "ShardSet",
    "read_manifest",
    "write_manifest",
    "verify_shards",
    "IMAGE_GZIP_LEVEL",
    "ARRAY_GZIP_LEVEL",
]

log = logging.getLogger(__name__)

MANIFEST_FORMAT = "deliffas-shards"
MANIFEST_NAME = "manifest.json"
META_NAME = "meta.h5"
SHARD_DIR = "shards"
IMAGE_GZIP_LEVEL = 4
"""gzip level of raw RGBA image chunks: at 1285x940 as small as PNG level 3 (-3 %), faster to
encode and decode (docs/shards.md)."""
ARRAY_GZIP_LEVEL = 4
"""gzip level (+ byte shuffle) of vertex chunks."""
NORMAL_MAP_COMPRESSION = None
"""Normal-map chunks are stored uncompressed: gzip 4 + shuffle made them 2.4x smaller (164 vs 386
KiB per float16 map at S = 256) but about 35x slower to read, and a training
item reads 2 (T + 1) maps, which made decoding them the largest part of loading an item
(docs/shards.md). Shards written with gzip maps are read as before."""

class ShardReadError(ValueError):
    """A shard that cannot be read as its schema says (corrupt, truncated or of another layout)."""


# --------------------------------------------------------------------------------------------- codec
@dataclass(frozen=True)
class Codec:
    """How images are stored in a shard.

    ``raw``: (N, C, H, W, 4) uint8 RGBA arrays, one gzip chunk per image (lossless, the default);
    ``png``: (N, C) RGBA PNG blobs (lossless); ``jpeg``: (N, C) RGB JPEG blobs of quality ``quality``
    (lossy) plus (N, C, H, W) gzip masks.
    """

    kind: Literal["raw", "png", "jpeg"] = "raw"
    quality: int = 95

    @classmethod
    def parse(cls, spec: str) -> "Codec":
        """``raw``, ``png`` or ``jpeg:Q`` (Q in 1..100, default 95)."""
        name, _, q = spec.partition(":")
        if name in ("raw", "png") and not q:
            return cls(name)  # type: ignore[arg-type]
        if name == "jpeg":
            quality = int(q) if q else 95
            if not 1 <= quality <= 100:
                raise ValueError(f"jpeg quality must be in 1..100, got {quality}")
            return cls("jpeg", quality)
        raise ValueError(f"codec must be raw, png or jpeg:Q, got {spec!r}")

    @property
    def spec(self) -> str:
        return f"jpeg:{self.quality}" if self.kind == "jpeg" else self.kind

    @property
    def lossless(self) -> bool:
        return self.kind != "jpeg"


def _vlen_u8():
    import h5py

    return h5py.vlen_dtype(np.uint8)


# --------------------------------------------------------------------------------------------- shard writer
@dataclass(frozen=True)
class ShardGeometry:
    """Per-frame geometry of a shard: its frames and their temporal-window predecessors.

    Attributes:
        frames: (G,) int64 sorted capture frame numbers.
        dofs: (G, D) float64 pose parameters in the template's units (zeros when the source had none).
        inner_verts: (G, V, 3) float32 mm, world frame, posed inner surface.
        outer_verts: (G, V, 3) float32 mm, world frame, outer surface (inner + d * vertex normal).
        normal_maps_inner: (G, 3, S, S) float16 unit world-space normals in [-1, 1], 0 off the atlas.
        normal_maps_outer: (G, 3, S, S) float16, the same for the outer surface.
    """

    frames: Integer[np.ndarray, "G"]
    dofs: Float[np.ndarray, "G D"]
    inner_verts: Float[np.ndarray, "G V 3"]
    outer_verts: Float[np.ndarray, "G V 3"]
    normal_maps_inner: Float[np.ndarray, "G 3 S S"]
    normal_maps_outer: Float[np.ndarray, "G 3 S S"]


_GEOMETRY_DTYPES = {"dofs": np.float64, "inner_verts": np.float32, "outer_verts": np.float32,
                    "normal_maps_inner": np.float16, "normal_maps_outer": np.float16}
"""The dtype each geometry dataset of a shard is stored in."""


class ShardWriter:
    """Writes one shard under a temporary name; ``commit`` renames it and returns (sha256, bytes).

    Args:
        path: final path ``<out>/shards/<sequence>-<k:05d>.h5``.
        sequence: ``training`` or ``testing``.
        frames: (N,) capture frames whose images the shard holds (sorted).
        camera_ids: (C,) calibration indices of the image columns.
        height: image height of every camera, pixels.
        width: image width of every camera, pixels.
        codec: image codec.
        geometry: the shard's geometry block (must contain every frame of ``window_rows``).
        window: T, predecessors per frame; ``window_rows[n, k]`` = geometry row of max(f_n - k, first).
        first_frame: the sequence's first frame (clamp of the temporal window).
    """

    def __init__(self, path: str | os.PathLike, sequence: str, frames: Sequence[int], camera_ids: Sequence[int],
                 height: int, width: int, codec: Codec, geometry: ShardGeometry, window: int, first_frame: int):
        import h5py

        self.path = Path(path)
        self.tmp = temp_path(self.path)
        self.codec = codec
        self.height, self.width = int(height), int(width)
        frames = np.asarray(frames, np.int64)
        cams = np.asarray(camera_ids, np.int64)
        gframes = np.asarray(geometry.frames, np.int64)
        want = np.maximum(frames[:, None] - np.arange(window + 1)[None], first_frame)  # (N, T+1)
        rows = np.searchsorted(gframes, want)
        if np.any(rows >= len(gframes)) or np.any(gframes[np.minimum(rows, len(gframes) - 1)] != want):
            raise ValueError(f"{self.path.name}: geometry lacks frames of the temporal window")
        # NaN/inf (or a value beyond the stored dtype) is refused before anything is written
        stored = {name: finite_as(f"{self.path}: geometry/{name}", getattr(geometry, name), dtype)
                  for name, dtype in _GEOMETRY_DTYPES.items()}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # no chunk cache: each chunk gets its file space when it is written, not when the last handle of
        # its dataset closes (a thread that briefly holds this frame, as Dask's profiler does, would
        # otherwise delay a close and reorder the chunks, and the shard's bytes would differ)
        self._f = h5py.File(self.tmp, "w", rdcc_nbytes=0)
        f = self._f
        f.attrs.update({"format": SHARD_FORMAT, "version": SCHEMA_VERSION, "sequence": sequence,
                        "codec": codec.spec, "window": int(window), "first_frame": int(first_frame),
                        "height": self.height, "width": self.width, "complete": 0})
        f.create_dataset("frames", data=frames)
        f.create_dataset("camera_ids", data=cams)
        f.create_dataset("window_rows", data=rows.astype(np.int64))
        N, C, H, W = len(frames), len(cams), self.height, self.width
        if codec.kind == "raw":
            f.create_dataset("rgba", (N, C, H, W, 4), np.uint8, chunks=(1, 1, H, W, 4),
                             compression="gzip", compression_opts=IMAGE_GZIP_LEVEL)
        elif codec.kind == "png":
            f.create_dataset("png", (N, C), _vlen_u8())
        else:
            f.create_dataset("jpeg", (N, C), _vlen_u8())
            f.create_dataset("masks", (N, C, H, W), np.uint8, chunks=(1, 1, H, W),
                             compression="gzip", compression_opts=IMAGE_GZIP_LEVEL)
        g = f.create_group("geometry")
        g.create_dataset("frames", data=gframes)
        g.create_dataset("dofs", data=stored["dofs"])
        for name in ("inner_verts", "outer_verts"):
            a = stored[name]
            g.create_dataset(name, data=a, chunks=(1,) + a.shape[1:], compression="gzip",
                             compression_opts=ARRAY_GZIP_LEVEL, shuffle=True)
        for name in ("normal_maps_inner", "normal_maps_outer"):
            a = stored[name]
            g.create_dataset(name, data=a, chunks=(1,) + a.shape[1:], compression=NORMAL_MAP_COMPRESSION)

    def put(self, row: int, col: int, rgb: np.ndarray, mask: np.ndarray) -> None:
        """Store the image of frame row ``row`` and camera column ``col``: rgb (H, W, 3), mask (H, W) uint8."""
        import cv2

        if rgb.shape != (self.height, self.width, 3) or mask.shape != (self.height, self.width):
            raise ValueError(f"{self.path.name}: image ({row}, {col}) expected {self.width}x{self.height}, "
                             f"got rgb {rgb.shape}, mask {mask.shape}")
        f = self._f
        if self.codec.kind == "raw":
            f["rgba"][row, col] = np.concatenate([rgb, mask[..., None]], axis=2)
        elif self.codec.kind == "png":
            bgra = np.concatenate([rgb[..., ::-1], mask[..., None]], axis=2)
            ok, buf = cv2.imencode(".png", bgra, [cv2.IMWRITE_PNG_COMPRESSION, 3])
            f["png"][row, col] = buf.ravel()
        else:
            ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                                   [cv2.IMWRITE_JPEG_QUALITY, self.codec.quality])
            f["jpeg"][row, col] = buf.ravel()
            f["masks"][row, col] = mask

    def commit(self) -> tuple[str, int]:
        """Mark complete, close, fsync and rename to the final name; returns (sha256, bytes)."""
        self._f.attrs["complete"] = 1
        self._f.close()
        durable_replace(self.tmp, self.path)
        return sha256_file(self.path), self.path.stat().st_size

    def abort(self) -> None:
        """Close and delete the temporary file."""
        try:
            self._f.close()
        finally:
            self.tmp.unlink(missing_ok=True)

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()


# --------------------------------------------------------------------------------------------- shard reader
class ShardFile:
    """Lazy reader of one shard; the h5py handle is opened on first access (in the current process)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._f = None
        self._pid = None
        self._datasets: dict[str, object] = {}

    @property
    def h5(self):
        import h5py

        if self._f is None or self._pid != os.getpid():  # never reuse a handle across fork
            self._f = h5py.File(self.path, "r")
            self._pid = os.getpid()
            self._datasets = {}
        return self._f

    def dataset(self, key: str):
        """The h5py dataset at ``key`` (e.g. ``"geometry/inner_verts"``), or None if absent;
        handles are kept, since an h5py name lookup costs about as much as reading a small chunk."""
        f = self.h5
        if key not in self._datasets:
            self._datasets[key] = f[key] if key in f else None
        return self._datasets[key]

    def close(self) -> None:
        if self._f is not None and self._pid == os.getpid():
            self._f.close()
        self._f = None
        self._datasets = {}

    def __getstate__(self):  # picklable for DataLoader workers (spawn): handles are reopened there
        return {"path": self.path}

    def __setstate__(self, state):
        self.__init__(state["path"])

    @property
    def frames(self) -> np.ndarray:
        return self.h5["frames"][()]

    @property
    def camera_ids(self) -> np.ndarray:
        return self.h5["camera_ids"][()]

    @property
    def codec(self) -> Codec:
        return Codec.parse(str(self.h5.attrs["codec"]))

    def rgba(self, row: int, col: int) -> np.ndarray:
        """(H, W, 4) uint8: RGB and mask of frame row ``row``, camera column ``col`` in one array."""
        f = self.h5
        if "rgba" in f:
            return f["rgba"][row, col]
        rgb, mask = self.image(row, col)
        return np.concatenate([rgb, mask[..., None]], axis=2)

    def rgba_many(self, row: int, cols: Sequence[int]) -> np.ndarray:
        """(K, H, W, 4) uint8 of frame row ``row`` and camera columns ``cols`` (any order), read in
        one call when the columns are adjacent."""
        cols = np.asarray(cols, np.int64)
        ds = self.dataset("rgba")
        if ds is None or len(cols) == 0:
            return np.stack([self.rgba(row, int(c)) for c in cols]) if len(cols) else np.zeros((0, 0, 0, 4), np.uint8)
        uniq, inverse = np.unique(cols, return_inverse=True)
        if uniq[-1] - uniq[0] + 1 == len(uniq):  # adjacent chunks: one slice read
            return ds[row, int(uniq[0]) : int(uniq[-1]) + 1][inverse]
        # h5py's point-list selection is pathologically slow: one read each
        return np.stack([ds[row, int(c)] for c in cols])

    def image(self, row: int, col: int) -> tuple[np.ndarray, np.ndarray]:
        """rgb (H, W, 3) uint8 and mask (H, W) uint8 of frame row ``row``, camera column ``col``."""
        import cv2

        f = self.h5
        if "rgba" in f:
            rgba = f["rgba"][row, col]
            return np.ascontiguousarray(rgba[..., :3]), np.ascontiguousarray(rgba[..., 3])
        if "png" in f:
            bgra = cv2.imdecode(f["png"][row, col], cv2.IMREAD_UNCHANGED)
            return cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGB), np.ascontiguousarray(bgra[..., 3])
        bgr = cv2.imdecode(f["jpeg"][row, col], cv2.IMREAD_COLOR)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), f["masks"][row, col]

    def geometry(self, name: str, rows: np.ndarray | Sequence[int | np.integer]) -> np.ndarray:
        """Rows of a geometry dataset (``dofs``, ``inner_verts``, ``normal_maps_outer``, …), in the given order."""
        rows = np.asarray(rows, np.int64)
        uniq, inverse = np.unique(rows, return_inverse=True)  # h5py wants increasing indices
        ds = self.dataset(f"geometry/{name}")
        if ds is None:
            raise KeyError(f"{self.path}: no geometry dataset {name!r}")
        if len(uniq) and uniq[-1] - uniq[0] + 1 == len(uniq):  # a slice: much cheaper in h5py than a point list
            return ds[int(uniq[0]) : int(uniq[-1]) + 1][inverse]
        return np.stack([ds[int(r)] for r in rows]) if len(rows) else ds[uniq]

    def check(self) -> None:
        """Read every dataset once; raises on unreadable or incomplete content."""
        f = self.h5
        if f.attrs.get("format") != SHARD_FORMAT or int(f.attrs.get("complete", 0)) != 1:
            raise ValueError("not a complete deliffas shard")
        for key in ("frames", "camera_ids", "window_rows"):
            f[key][()]
        for key in ("rgba", "png", "jpeg", "masks"):
            if key in f:
                for row in range(f[key].shape[0]):  # chunk by chunk, bounded memory
                    f[key][row]
        for key in f["geometry"]:
            f["geometry"][key][()]


# --------------------------------------------------------------------------------------------- manifest
def read_manifest(out_dir: str | os.PathLike) -> dict:
    """The parsed ``manifest.json`` of an output folder (FileNotFoundError / ValueError when missing or bad)."""
    p = Path(out_dir) / MANIFEST_NAME
    try:
        data = json.loads(p.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{p}: not valid UTF-8 JSON ({err})") from None
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"{p}: not a deliffas shard manifest")
    return data


def write_manifest(out_dir: str | os.PathLike, manifest: dict) -> None:
    """Write ``manifest.json`` atomically with sorted keys (deterministic bytes)."""
    p = Path(out_dir) / MANIFEST_NAME
    tmp = temp_path(p)
    tmp.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    durable_replace(tmp, p)


@dataclass(frozen=True)
class ShardInfo:
    """One complete shard as the manifest lists it."""

    name: str
    path: Path
    sequence: str
    frames: tuple[int, ...]
    sha256: str
    bytes: int


class ShardSet:
    """The complete shards of an output folder, as listed by its manifest.

    A conversion still running adds shards to the manifest as they finish; ``refresh`` re-reads it.
    File handles are opened lazily per process (safe with DataLoader workers).
    """

    def __init__(self, out_dir: str | os.PathLike):
        self.out_dir = Path(out_dir)
        self._files: dict[str, ShardFile] = {}
        self._meta: ShardMeta | None = None
        self.refresh()

    def refresh(self) -> None:
        """Re-read the manifest (new complete shards become visible)."""
        m = read_manifest(self.out_dir)
        structure = _manifest_structure_problems(m)
        if structure:
            raise ValueError(f"{self.out_dir / MANIFEST_NAME}: {structure[0]}")
        outside = [s["name"] for s in [m["meta"]] + m["shards"] if not inside(self.out_dir, s["name"])]
        if outside:
            raise ValueError(f"{self.out_dir / MANIFEST_NAME}: names a file outside the output folder: {outside[0]!r}")
        self.manifest = m
        self.complete = bool(m.get("complete", False))
        self.shards = [ShardInfo(s["name"], self.out_dir / s["name"], s["sequence"], tuple(s["frames"]),
                                 s["sha256"], int(s["bytes"])) for s in m.get("shards", [])]
        self._index = {(s.sequence, f): (k, row) for k, s in enumerate(self.shards) for row, f in enumerate(s.frames)}

    @property
    def meta(self) -> ShardMeta:
        if self._meta is None:
            self._meta = read_meta(self.out_dir / self.manifest["meta"]["name"])
        return self._meta

    def frames(self, sequence: str) -> list[int]:
        """Sorted frames of ``sequence`` held by complete shards."""
        return sorted(f for (seq, f) in self._index if seq == sequence)

    def locate(self, sequence: str, frame: int) -> tuple[ShardFile, int]:
        """(shard reader, frame row) holding ``frame`` of ``sequence``; KeyError when no complete shard has it.

        A shard is checked against its manifest entry and ``meta.h5`` once per process, when first opened (the
        schema checks of ``verify``, without the checksum: small datasets and dtypes only), so a frame table that
        maps a frame to another frame's row, or images of another dtype, are never served.

        Raises:
            ShardReadError: the shard does not match its schema (names the shard and the first problem).
        """
        k, row = self._index[(sequence, int(frame))]
        info = self.shards[k]
        f = self._files.get(info.name)
        if f is None:
            f = ShardFile(info.path)
            try:
                problems = shard_problems(f.h5, info.frames, self.meta)
            except (OSError, KeyError, ValueError, TypeError) as err:  # h5py's errors on damaged files
                problems = [f"{type(err).__name__}: {str(err)[:160]}"]
            if problems:
                f.close()
                raise ShardReadError(f"{info.path}: cannot read frame {frame} ({problems[0]}); run "
                                     f"`deliffas verify {self.out_dir}`")
            self._files[info.name] = f
        return f, row

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()

    def __getstate__(self):
        return {"out_dir": self.out_dir, "manifest": self.manifest, "meta": self._meta}

    def __setstate__(self, state):
        self.out_dir = state["out_dir"]
        self._files = {}
        self._meta = state["meta"]
        m = state["manifest"]
        self.manifest = m
        self.complete = bool(m.get("complete", False))
        self.shards = [ShardInfo(s["name"], self.out_dir / s["name"], s["sequence"], tuple(s["frames"]),
                                 s["sha256"], int(s["bytes"])) for s in m.get("shards", [])]
        self._index = {(s.sequence, f): (k, row) for k, s in enumerate(self.shards) for row, f in enumerate(s.frames)}


def open_shard_set(shards: ShardSet | str | os.PathLike) -> ShardSet:
    """``shards`` itself when it is a :class:`ShardSet`, else the shard set of that folder.

    A command opens its shard set once and passes it down; functions that also accept a folder call this.
    """
    return shards if isinstance(shards, ShardSet) else ShardSet(shards)


# --------------------------------------------------------------------------------------------- verify
def verify_conversion(config: VerifyConfig) -> ShardVerification:
    """:func:`verify_shards` of a folder a user names.

    Raises:
        FileNotFoundError: the folder holds no manifest (not a folder ``deliffas convert`` wrote).
    """
    out = Path(config.out)
    if not (out / MANIFEST_NAME).is_file():
        raise FileNotFoundError(f"{out}: no {MANIFEST_NAME} there; give the folder written by 'deliffas convert'")
    return verify_shards(out, deep=not config.quick)


def verify_shards(out_dir: str | os.PathLike, deep: bool = True) -> ShardVerification:
    """Check an output folder against its manifest; the result lists one message per problem (none = all good).

    Checks: manifest readable and of the documented structure; every name inside the output folder;
    ``meta.h5`` and every listed shard present, of the recorded size and sha256; every shard of the
    schema of docs/shards.md (datasets, shapes, dtypes, frames equal to the manifest's, index ranges:
    :func:`deliffas.data.shard_schema.shard_problems`); ``deep``: every dataset read once; every
    planned shard listed as complete (otherwise the conversion is unfinished).
    """
    out = Path(out_dir)
    try:
        m = read_manifest(out)
    except FileNotFoundError:
        return ShardVerification(out, deep, 0, (f"{out / MANIFEST_NAME}: missing (no conversion here, or it never "
                                                "started)",))
    except ValueError as err:
        return ShardVerification(out, deep, 0, (str(err),))
    structure = _manifest_structure_problems(m)
    if structure:
        return ShardVerification(out, deep, 0, tuple(f"{MANIFEST_NAME}: {p}" for p in structure))
    return ShardVerification(out, deep, len(m["shards"]), tuple(_listed_file_problems(out, m, deep)))


def _listed_file_problems(out: Path, m: dict, deep: bool) -> list[str]:
    """``verify_shards``'s checks of the files a well-formed manifest ``m`` lists."""
    import h5py

    problems: list[str] = []
    meta = None
    entries = [dict(m["meta"], kind="meta")] + [dict(s, kind="shard") for s in m["shards"]]
    for e in entries:
        if not inside(out, e["name"]):
            problems.append(f"{e['name']}: outside the output folder; refused")
            continue
        p = out / e["name"]
        if not p.is_file():
            problems.append(f"{e['name']}: missing {e['kind']} file")
            continue
        size = p.stat().st_size
        sha = sha256_file(p)
        if size != int(e["bytes"]) or sha != e["sha256"]:
            problems.append(f"{e['name']}: checksum mismatch (sha256 {sha[:12]}…, {size} bytes; manifest "
                            f"{e['sha256'][:12]}…, {e['bytes']} bytes)")
        try:
            if e["kind"] == "meta":
                meta = read_meta(p)
                continue
            with h5py.File(p, "r") as f:
                problems += [f"{e['name']}: {q}" for q in shard_problems(f, e["frames"], meta)]
            if deep:
                reader = ShardFile(p)
                try:
                    reader.check()
                finally:
                    reader.close()
        except Exception as err:  # any HDF5/IO failure is "unreadable"
            problems.append(f"{e['name']}: unreadable ({type(err).__name__}: {str(err)[:120]})")
    done = {s["name"] for s in m["shards"]}
    missing = [s["name"] for s in m.get("planned", []) if s["name"] not in done]
    for name in missing:
        problems.append(f"{name}: planned but not converted (conversion incomplete; rerun with --resume)")
    if not missing and not m.get("complete", False):
        problems.append(f"{MANIFEST_NAME}: not marked complete")
    return problems


def _manifest_structure_problems(m: dict) -> list[str]:
    """What a manifest lacks of its documented structure (docs/shards.md, manifest.json)."""
    problems = []
    meta = m.get("meta")
    if not isinstance(meta, dict) or not {"name", "sha256", "bytes"} <= set(meta):
        problems.append("'meta' must be an object with name, sha256 and bytes")
    shards = m.get("shards")
    if not isinstance(shards, list):
        return problems + ["'shards' must be a list"]
    for i, s in enumerate(shards):
        if not isinstance(s, dict) or not {"name", "sequence", "frames", "sha256", "bytes"} <= set(s):
            problems.append(f"shards[{i}] must be an object with name, sequence, frames, sha256 and bytes")
        elif not isinstance(s["frames"], list) or not all(isinstance(x, int) for x in s["frames"]):
            problems.append(f"shards[{i}].frames must be a list of frame numbers")
    planned = m.get("planned", [])
    if not isinstance(planned, list) or not all(isinstance(s, dict) and "name" in s for s in planned):
        problems.append("'planned' must be a list of objects with a name")
    return problems