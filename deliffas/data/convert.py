"""Conversion of a DynaCap subject folder (either frame layout) into sharded HDF5 (docs/shards.md).

``convert(subject_dir, out_dir, ConvertConfig)`` plans shards of consecutive selected frames per
sequence, writes ``meta.h5``, converts the shards (in-process or in spawned worker processes), and
rewrites ``manifest.json`` atomically after every finished shard. ``resume`` keeps the shards the
manifest lists whose checksum still matches, and re-adds shards that reached their final name
before the manifest was updated. The subject folder is only read.

Per frame the surface is the skinned template (``DDCTemplate.pose`` of the sequence's motion), or a
tracked ``.meshes`` sequence, or the template of a variant folder; the outer surface is the inner
one moved by d (30 mm, or per vertex from the variant's ``outer.obj``) along the vertex normals.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.data.shards import (
    MANIFEST_NAME,
    META_NAME,
    SCHEMA_VERSION,
    SHARD_DIR,
    Codec,
    ShardGeometry,
    ShardMeta,
    ShardWriter,
    read_manifest,
    sha256_file,
    write_manifest,
    write_meta,
)

__all__ = ["ConvertConfig", "ConvertResult", "convert", "parse_frame_range", "process_map", "SEQUENCES"]

log = logging.getLogger(__name__)

SEQUENCES = ("training", "testing")


@dataclass(frozen=True)
class ConvertConfig:
    """What ``convert`` writes."""

    frames: str | None = None
    """``A:B:STEP`` (Python slice of capture frame indices, any part may be empty); None = every frame."""
    cameras: tuple[int, ...] | None = None
    """Calibration indices to convert; None = every camera."""
    sequences: tuple[str, ...] | None = None
    """Sequence folders to convert; None = those of ``training``/``testing`` present."""
    shard_frames: int = 10
    """Selected frames per shard."""
    jobs: int = 1
    """Worker processes (spawned); 1 = in this process."""
    resume: bool = False
    """Keep complete shards of an earlier run with the same configuration."""
    overwrite: bool = False
    """Delete an existing conversion in ``out_dir`` first."""
    meshes: tuple[str, ...] = ()
    """Tracked surfaces ``[SEQUENCE=]FILE.meshes`` (default sequence: training) instead of the skinned template."""
    template: str | None = None
    """A template variant folder (its ``.character`` + optional ``outer.obj``) or ``.character`` file."""
    atlas_res: int = 256
    """S, the normal-map side (the paper uses 1024)."""
    offset_mm: float = 30.0
    """d of the outer surface (when no ``outer.obj`` gives per-vertex offsets)."""
    codec: str = "raw"
    """Image codec: ``raw`` (lossless gzip arrays), ``png`` or ``jpeg:Q``."""
    window: int = 2
    """T: predecessors stored per frame for temporal normal maps (f, f-1, ..., f-T)."""
    layout: Literal["auto", "images", "videos"] = "auto"
    """Frame layout of the subject (auto: images when present, else videos)."""
    skinning: Literal["dqs", "lbs"] = "dqs"
    """Skinning of the template."""
    test_cameras: tuple[int, ...] | None = None
    """Held-out cameras; None = the subject's ``split.json`` / ``test_cameras.txt`` (or none)."""
    gutter: int = 2
    """Texel-table gutter rings."""
    masks: str | None = None
    """Mask folder inside each sequence folder (e.g. ``foregroundSegmentation``) replacing alpha / fg videos."""
    progress: bool = True
    """Show a tqdm progress bar."""


@dataclass(frozen=True)
class ConvertResult:
    """What a ``convert`` call did."""

    out_dir: Path
    shards_total: int
    shards_converted: int
    shards_skipped: int
    frames_converted: int
    images_converted: int
    seconds: float
    seconds_setup: float
    bytes_total: int


def parse_frame_range(spec: str | None) -> slice:
    """``A:B:STEP`` -> slice (empty parts = open); a single integer ``A`` means just frame A."""
    if spec is None or spec == "":
        return slice(None)
    parts = spec.split(":")
    try:
        vals = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise ValueError(f"frames must be A:B:STEP with integers, got {spec!r}") from None
    if len(vals) == 1:
        return slice(vals[0], vals[0] + 1)
    if len(vals) > 3:
        raise ValueError(f"frames must be A:B:STEP, got {spec!r}")
    vals += [None] * (3 - len(vals))
    if vals[2] is not None and vals[2] <= 0:
        raise ValueError(f"frames: STEP must be positive, got {vals[2]}")
    return slice(*vals)


def _select(frames: np.ndarray, sl: slice) -> np.ndarray:
    a = frames.min() if sl.start is None else sl.start
    b = frames.max() + 1 if sl.stop is None else sl.stop
    step = sl.step or 1
    keep = (frames >= a) & (frames < b) & ((frames - a) % step == 0)
    return frames[keep]


# --------------------------------------------------------------------------------------------- processes
def process_map(fn, tasks: Sequence[tuple], jobs: int, initializer=None, initargs: tuple = (), poll_s: float = 2.0):
    """Run ``fn(*task)`` for every task in ``jobs`` spawned processes; yield results as they complete.

    Spawn (not fork) keeps torch/open3d/h5py state out of the workers. A worker that dies (e.g. a
    signal) raises RuntimeError naming its pid and exit code instead of hanging; on any error the
    remaining workers (started here) are terminated by handle. Keep ``tasks`` small and put large
    arrays into ``initargs``: CPython's executor can deadlock when a worker dies while a task larger
    than the pipe buffer (64 kB) is being written to it. Workers die with the calling process, even
    when it is killed with SIGKILL (``_exit_when_parent_dies``), so no orphan keeps writing. Callers
    need the ``if __name__ == "__main__"`` guard in their main script (spawn re-imports it).
    """
    pool = ProcessPoolExecutor(jobs, mp_context=get_context("spawn"), initializer=_worker_init,
                               initargs=(os.getpid(), initializer, initargs))
    try:
        pending = {pool.submit(fn, *t) for t in tasks}
        while pending:
            done, pending = wait(pending, timeout=poll_s, return_when=FIRST_COMPLETED)
            for fut in done:
                yield fut.result()
            dead = [p for p in list(getattr(pool, "_processes", {}).values()) if p.exitcode not in (None, 0)]
            if dead and pending:
                raise RuntimeError(f"worker process {dead[0].pid} died (exit code {dead[0].exitcode}); "
                                   f"{len(pending)} tasks unfinished")
    except BaseException:
        for proc in list(getattr(pool, "_processes", {}).values()):
            if proc.is_alive():
                proc.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


_PR_SET_PDEATHSIG = 1


def _exit_when_parent_dies(parent_pid: int) -> None:
    """Make this worker die with the process that started it (even by SIGKILL).

    Without it, workers of a killed ``convert --jobs N`` live on as orphans and keep renaming shards
    into the output folder while a ``--resume`` or ``--overwrite`` runs there. Linux: the kernel
    sends SIGKILL on the parent's death (``PR_SET_PDEATHSIG``); elsewhere a daemon thread polls the
    parent id every 0.2 s.
    """
    import signal
    import sys
    import threading

    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
                if os.getppid() != parent_pid:  # died before prctl took effect
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.2)
        os._exit(1)

    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _worker_init(parent_pid: int, initializer, initargs: tuple) -> None:
    _exit_when_parent_dies(parent_pid)
    if initializer is not None:
        initializer(*initargs)


# --------------------------------------------------------------------------------------------- planning
@dataclass(frozen=True)
class _Sequence:
    name: str
    seq_dir: Path
    frames: np.ndarray  # selected
    first_frame: int
    motion: Path | None
    meshes: Path | None
    width: int
    height: int


@dataclass(frozen=True)
class _Task:
    name: str
    sequence: str
    frames: tuple[int, ...]
    geometry_frames: tuple[int, ...]


@dataclass(frozen=True)
class _Context:
    """Everything a worker needs (picklable paths and settings)."""

    subject: Path
    out_dir: Path
    character: Path
    outer_obj: Path | None
    camera_names: tuple[str, ...]
    converted: tuple[int, ...]
    sequences: dict
    config: ConvertConfig


def _find_character(subject: Path, template: str | None) -> tuple[Path, Path | None]:
    if template is not None:
        t = Path(template)
        if t.is_file() and t.suffix == ".character":
            outer = t.parent / "outer.obj"
            return t, outer if outer.is_file() else None
        found = sorted(t.glob("*.character")) if t.is_dir() else []
        if len(found) != 1:
            raise FileNotFoundError(f"--template {t}: expected a folder with one .character, found {len(found)}")
        outer = t / "outer.obj"
        return found[0], outer if outer.is_file() else None
    for d in (subject / "character", subject):
        found = sorted(d.glob("*.character")) if d.is_dir() else []
        if len(found) == 1:
            return found[0], None
        if len(found) > 1:
            raise FileNotFoundError(f"{d}: several .character files {[p.name for p in found]}; pass --template")
    raise FileNotFoundError(f"{subject}: no character/<name>.character; pass --template")


def _find_motion(seq_dir: Path) -> Path | None:
    p = seq_dir / "poses.motion"
    if p.is_file():
        return p
    found = sorted((seq_dir / "motions").glob("*.motion")) if (seq_dir / "motions").is_dir() else []
    return found[0] if found else None


def _parse_meshes(specs: Sequence[str]) -> dict[str, Path]:
    out = {}
    for s in specs:
        seq, sep, path = s.partition("=")
        if not sep:
            seq, path = "training", s
        if seq in out:
            raise ValueError(f"--meshes given twice for sequence {seq}")
        out[seq] = Path(path).resolve()
    return out


def _image_size(seq_dir: Path, layout: str, camera_names: Sequence[str]) -> tuple[int, int, str]:
    import cv2

    from deliffas.io.frames import _resolve_video, find_image_folder

    folder = find_image_folder(seq_dir) if layout in ("auto", "images") else None
    if folder is not None:
        w, h = folder.name.split("_")[1:3]
        return int(w), int(h), "images"
    if layout in ("auto", "videos") and (seq_dir / "img").is_dir():
        cap = cv2.VideoCapture(str(_resolve_video(seq_dir, "img", camera_names[0])))
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        cap.release()
        return w, h, "videos"
    raise FileNotFoundError(f"{seq_dir}: no frames ({'rgb_<W>_<H>/ or img/' if layout == 'auto' else layout})")


def _split(subject: Path, num_cameras: int, override: Sequence[int] | None) -> list[int]:
    if override is not None:
        return sorted({int(c) for c in override})
    sj = subject / "split.json"
    if sj.is_file():
        return sorted(int(c) for c in json.loads(sj.read_text()).get("test_cameras", []))
    tc = subject / "test_cameras.txt"
    if tc.is_file():
        return sorted(int(tok) for tok in tc.read_text().split())
    return []


def _character_hash(character_path: Path, outer_obj: Path | None) -> str:
    from deliffas.io.dynacap import read_character_files

    files = read_character_files(character_path)
    h = hashlib.sha256()
    for p in (character_path, files.skeleton, files.mesh, files.skin, files.pose, outer_obj):
        if p is not None:
            h.update(Path(p).name.encode() + b"\0" + Path(p).read_bytes())
    return h.hexdigest()


def _plan(subject: Path, out_dir: Path, config: ConvertConfig):
    from deliffas.io.dynacap import read_calibration, read_meshes, read_motion

    calib = subject / "cameras.calibration"
    cameras = read_calibration(calib)
    names = tuple(c.name for c in cameras)
    if config.cameras is not None:
        converted = sorted({int(c) for c in config.cameras})
        if not converted or converted[0] < 0 or converted[-1] >= len(cameras):
            raise ValueError(f"--cameras {list(config.cameras)}: indices must be in [0, {len(cameras)})")
    else:
        converted = list(range(len(cameras)))
    character, outer_obj = _find_character(subject, config.template)
    meshes = _parse_meshes(config.meshes)
    seq_names = config.sequences or tuple(s for s in SEQUENCES if (subject / s).is_dir())
    if not seq_names:
        raise FileNotFoundError(f"{subject}: no training/ or testing/ sequence folder")
    sl = parse_frame_range(config.frames)
    seqs: dict[str, _Sequence] = {}
    motions = {}
    size = None
    for seq in seq_names:
        seq_dir = subject / seq
        if not seq_dir.is_dir():
            raise FileNotFoundError(f"{seq_dir}: sequence folder not found")
        w, h, layout = _image_size(seq_dir, config.layout, names)
        if size is not None and size != (w, h):
            raise ValueError(f"{seq}: images are {w}x{h}, other sequences {size[0]}x{size[1]}")
        size = (w, h)
        motion_path = _find_motion(seq_dir)
        mesh_path = meshes.get(seq)
        if mesh_path is not None:
            avail = read_meshes(mesh_path).frames
        elif motion_path is not None:
            avail = read_motion(motion_path).frames
        else:
            raise FileNotFoundError(f"{seq_dir}: no poses.motion (and no --meshes {seq}=FILE)")
        if motion_path is not None:
            motions[seq] = read_motion(motion_path)
        avail = np.unique(np.asarray(avail, np.int64))
        selected = _select(avail, sl)
        if layout == "images":
            from deliffas.io.frames import ImageFolderSource

            have = set(ImageFolderSource(seq_dir).frames())
            missing = [int(f) for f in selected if int(f) not in have]
            if missing:
                log.warning("%s: %d selected frames have no image folder (first %d); skipped", seq, len(missing), missing[0])
                selected = np.array([f for f in selected if int(f) in have], np.int64)
        if len(selected) == 0:
            raise ValueError(f"{seq}: no frames selected by --frames {config.frames!r}")
        seqs[seq] = _Sequence(seq, seq_dir, selected, int(avail.min()), motion_path, mesh_path, w, h)
    tasks = []
    for seq, s in seqs.items():
        for k in range(0, len(s.frames), config.shard_frames):
            fr = s.frames[k: k + config.shard_frames]
            geo = np.unique(np.maximum(fr[:, None] - np.arange(config.window + 1)[None], s.first_frame))
            tasks.append(_Task(f"{SHARD_DIR}/{seq}-{k // config.shard_frames:05d}.h5", seq,
                               tuple(int(f) for f in fr), tuple(int(f) for f in geo)))
    test = [c for c in _split(subject, len(cameras), config.test_cameras) if c in converted]
    train = [c for c in converted if c not in test]
    ctx = _Context(subject, out_dir, character, outer_obj, names, tuple(converted),
                   {k: asdict(v) for k, v in seqs.items()}, config)
    return cameras, train, test, seqs, tasks, ctx


def _manifest_config(subject: Path, config: ConvertConfig, character: Path) -> dict:
    keep = {k: v for k, v in asdict(config).items() if k not in ("jobs", "resume", "overwrite", "progress")}
    keep["subject"] = str(subject)
    keep["character"] = str(character)
    return json.loads(json.dumps(keep))  # tuples -> lists, as read back from JSON


# --------------------------------------------------------------------------------------------- workers
_STATE: dict = {}


@contextlib.contextmanager
def _single_thread_torch():
    """Geometry runs with one torch thread so results do not depend on --jobs (and workers do not oversubscribe)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _state(ctx: _Context) -> dict:
    """Per-process cache: character, template, offsets, normal-map gather, motions, meshes."""
    key = (str(ctx.out_dir), str(ctx.character), ctx.config)
    if _STATE.get("key") == key:
        return _STATE
    import torch

    from deliffas.io.dynacap import read_character, read_meshes, read_motion, read_obj
    from deliffas.geometry.atlas import UVAtlas, uv_texel_table
    from deliffas.geometry.frame_geometry import FrameGeometryBuilder
    from deliffas.geometry.mesh_ops import vertex_normals
    from deliffas.geometry.template import DDCTemplate

    character = read_character(ctx.character)
    mesh = character.mesh
    if mesh.face_uvs is None:
        raise ValueError(f"{character.files.mesh}: the template has no per-corner uvs (vt); needed for normal maps")
    faces = np.asarray(mesh.faces, np.int64)
    if ctx.outer_obj is not None:
        outer = read_obj(ctx.outer_obj)
        if outer.num_verts != mesh.num_verts:
            raise ValueError(f"{ctx.outer_obj}: {outer.num_verts} vertices, template has {mesh.num_verts}")
        n_rest = vertex_normals(np.asarray(mesh.verts, np.float64), faces)
        offsets = np.einsum("vc,vc->v", outer.verts - mesh.verts, n_rest).astype(np.float32)
    else:
        offsets = np.full(mesh.num_verts, ctx.config.offset_mm, np.float32)
    table = uv_texel_table(UVAtlas(mesh.uvs, mesh.face_uvs), ctx.config.atlas_res, ctx.config.gutter)
    seqs = {k: _Sequence(**v) for k, v in ctx.sequences.items()}
    _STATE.clear()
    _STATE.update(
        key=key, character=character, faces=faces, offsets=offsets, table=table,
        builder=FrameGeometryBuilder(faces, offsets, table, dtype=torch.float16),
        template=DDCTemplate(character, ctx.config.skinning, dtype=torch.float64),
        motions={k: read_motion(s.motion, character.skeleton.num_dofs) for k, s in seqs.items() if s.motion},
        meshes={k: read_meshes(s.meshes, mesh.num_verts) for k, s in seqs.items() if s.meshes},
        sequences=seqs,
    )
    return _STATE


def _geometry(st: dict, sequence: str, frames: Sequence[int]) -> ShardGeometry:
    import torch

    frames = np.asarray(frames, np.int64)
    motion = st["motions"].get(sequence)
    num_dofs = st["character"].skeleton.num_dofs
    if motion is not None:
        try:
            rows = np.array([motion.row_of(int(f)) for f in frames])
        except KeyError as err:
            raise ValueError(f"{sequence}: motion lacks a frame of the temporal window ({err.args[0]})") from None
        dofs = motion.dofs[rows]
    else:
        dofs = np.zeros((len(frames), num_dofs))
    seq_meshes = st["meshes"].get(sequence)
    if seq_meshes is not None:
        index = {int(f): i for i, f in enumerate(seq_meshes.frames)}
        missing = [int(f) for f in frames if int(f) not in index]
        if missing:
            raise ValueError(f"{sequence}: .meshes lacks frame {missing[0]} (needed by the temporal window)")
        inner = seq_meshes.verts[[index[int(f)] for f in frames]].astype(np.float64)
    else:
        with torch.no_grad():
            inner = st["template"].pose(torch.as_tensor(dofs, dtype=torch.float64)).numpy()
    geo = st["builder"].build(inner)
    return ShardGeometry(frames, dofs, geo.inner, geo.outer, geo.normal_maps_inner.numpy(),
                         geo.normal_maps_outer.numpy())


def _convert_shard(ctx: _Context, task: _Task) -> dict:
    """Write one shard; returns its manifest entry. Runs in a worker process or in-process."""
    from deliffas.io.frames import open_frame_source

    t0 = time.perf_counter()
    with _single_thread_torch():
        st = _state(ctx)
        geo = _geometry(st, task.sequence, task.geometry_frames)
    seq = st["sequences"][task.sequence]
    mask_dir = seq.seq_dir / ctx.config.masks if ctx.config.masks else None
    src = open_frame_source(seq.seq_dir, ctx.camera_names, ctx.config.layout, seq.first_frame, mask_dir)
    writer = ShardWriter(ctx.out_dir / task.name, task.sequence, task.frames, ctx.converted, seq.height, seq.width,
                         Codec.parse(ctx.config.codec), geo, ctx.config.window, seq.first_frame)
    try:
        for col, cam in enumerate(ctx.converted):  # camera-major: each video is decoded forward once
            for row, frame in enumerate(task.frames):
                rgb, mask = src.read(frame, cam)
                writer.put(row, col, rgb, mask)
        sha, size = writer.commit()
    except BaseException:
        writer.abort()
        raise
    finally:
        src.close()
    return {"name": task.name, "sequence": task.sequence, "frames": list(task.frames), "sha256": sha,
            "bytes": size, "seconds": time.perf_counter() - t0}


# --------------------------------------------------------------------------------------------- main entry
def _warn_if_not_watertight(character: Path, faces: np.ndarray) -> None:
    """Log where a template has holes: rays through them see no inner surface (the outer exit is used)."""
    from deliffas.geometry.shell import mesh_edges

    edges, counts, _ = mesh_edges(np.asarray(faces, np.int64))
    boundary = np.unique(edges[counts == 1])
    if len(boundary) or np.any(counts > 2):
        log.warning("%s: the template is not watertight: %d boundary vertices (first ids %s), %d non-manifold edges",
                    character, len(boundary), boundary[:10].tolist(), int(np.sum(counts > 2)))


def _build_meta(cameras: list[Camera], train, test, seqs, ctx: _Context) -> ShardMeta:
    with _single_thread_torch():
        st = _state(ctx)
    w, h = next(iter(seqs.values())).width, next(iter(seqs.values())).height
    scaled = [c.rescaled(w, h) if (c.width, c.height) != (w, h) else c for c in cameras]
    mesh = st["character"].mesh
    _warn_if_not_watertight(ctx.character, mesh.faces)
    table = st["table"]
    cfg = ctx.config
    attrs = {
        "subject": str(ctx.subject), "character_path": str(ctx.character), "character": str(ctx.character),
        "character_sha256": _character_hash(ctx.character, ctx.outer_obj),
        "outer_obj": str(ctx.outer_obj) if ctx.outer_obj else "",
        "surface": "meshes" if cfg.meshes else ("variant" if cfg.template else "template"),
        "meshes": json.dumps(list(cfg.meshes)), "skinning": cfg.skinning, "offset_mm": float(cfg.offset_mm),
        "codec": Codec.parse(cfg.codec).spec, "window": int(cfg.window), "atlas_res": int(cfg.atlas_res),
        "gutter": int(cfg.gutter), "shard_frames": int(cfg.shard_frames),
    }
    return ShardMeta(
        camera_names=[c.name for c in scaled], K=np.stack([c.K for c in scaled]),
        world_to_cam=np.stack([c.world_to_cam for c in scaled]),
        sizes=np.array([[c.width, c.height] for c in scaled], np.int64),
        converted_cameras=np.asarray(ctx.converted, np.int64), train_cameras=np.asarray(train, np.int64),
        test_cameras=np.asarray(test, np.int64),
        sequence_frames={k: s.frames for k, s in seqs.items()}, first_frames={k: s.first_frame for k, s in seqs.items()},
        faces=mesh.faces, uvs=mesh.uvs, face_uvs=mesh.face_uvs, rest_verts=mesh.verts, outer_offsets=st["offsets"],
        texel_face=table.face.astype(np.int32), texel_bary=table.bary, texel_valid=table.valid, attrs=attrs)


def convert(subject_dir: str | os.PathLike, out_dir: str | os.PathLike, config: ConvertConfig = ConvertConfig()) -> ConvertResult:
    """Convert a subject folder into shards + ``meta.h5`` + ``manifest.json`` under ``out_dir``."""
    from tqdm import tqdm

    t_start = time.perf_counter()
    subject = Path(subject_dir).resolve()
    out = Path(out_dir).resolve()
    if out == subject or subject in out.parents:
        raise ValueError(f"output {out} lies inside the source folder {subject}; the source is never written to")
    if config.shard_frames < 1 or config.window < 0 or config.atlas_res < 4:
        raise ValueError("shard_frames >= 1, window >= 0 and atlas_res >= 4 are required")
    Codec.parse(config.codec)
    cameras, train, test, seqs, tasks, ctx = _plan(subject, out, config)
    mconfig = _manifest_config(subject, config, ctx.character)
    old = None
    if (out / MANIFEST_NAME).is_file():
        if config.overwrite:
            shutil.rmtree(out / SHARD_DIR, ignore_errors=True)
            (out / MANIFEST_NAME).unlink()
            (out / META_NAME).unlink(missing_ok=True)
        elif not config.resume:
            raise FileExistsError(f"{out}: holds a conversion already; use --resume or --overwrite")
        else:
            old = read_manifest(out)
            if old.get("config") != mconfig:
                diff = sorted(k for k in set(mconfig) | set(old.get("config", {}))
                              if mconfig.get(k) != old.get("config", {}).get(k))
                raise ValueError(f"{out}: --resume with a different configuration (differs in {diff})")
    (out / SHARD_DIR).mkdir(parents=True, exist_ok=True)
    for leftover in list((out / SHARD_DIR).glob(".*.tmp-*")) + list(out.glob(".*.tmp-*")):
        log.info("removing leftover temporary file %s", leftover.name)
        leftover.unlink(missing_ok=True)

    meta = _build_meta(cameras, train, test, seqs, ctx)
    meta_sha, meta_bytes = write_meta(out / META_NAME, meta)
    done: dict[str, dict] = {}
    if old is not None:
        listed = {s["name"]: s for s in old.get("shards", [])}
        for t in tasks:
            p = out / t.name
            if not p.is_file():
                continue
            sha = sha256_file(p)
            entry = listed.get(t.name)
            if entry is not None and entry["sha256"] == sha and entry["frames"] == list(t.frames):
                done[t.name] = entry
            elif entry is None and _is_complete_shard(p, t):
                done[t.name] = {"name": t.name, "sequence": t.sequence, "frames": list(t.frames),
                                "sha256": sha, "bytes": p.stat().st_size}  # renamed before the manifest update
            else:
                log.warning("%s: does not match the manifest; converting it again", t.name)
    planned = [{"name": t.name, "sequence": t.sequence, "frames": list(t.frames)} for t in tasks]
    order = {t.name: i for i, t in enumerate(tasks)}

    def manifest(complete: bool) -> dict:
        shards = sorted(done.values(), key=lambda e: order[e["name"]])
        return {"format": "deliffas-shards", "version": SCHEMA_VERSION, "complete": complete, "config": mconfig,
                "meta": {"name": META_NAME, "sha256": meta_sha, "bytes": meta_bytes}, "planned": planned,
                "shards": [{k: e[k] for k in ("name", "sequence", "frames", "sha256", "bytes")} for e in shards]}

    write_manifest(out, manifest(len(done) == len(tasks)))
    pending = [t for t in tasks if t.name not in done]
    skipped = len(tasks) - len(pending)
    setup = time.perf_counter() - t_start
    frames_done = 0
    bar = tqdm(total=len(tasks), initial=skipped, unit="shard", desc="convert", disable=not config.progress)

    def record(entry: dict) -> None:
        nonlocal frames_done
        done[entry["name"]] = entry
        frames_done += len(entry["frames"])
        write_manifest(out, manifest(False))
        bar.update(1)
        bar.set_postfix(frames_s=f"{frames_done / max(time.perf_counter() - t_start, 1e-9):.2f}")

    try:
        if config.jobs <= 1 or len(pending) <= 1:
            for t in pending:
                record(_convert_shard(ctx, t))
        else:
            for entry in process_map(_convert_shard, [(ctx, t) for t in pending], min(config.jobs, len(pending))):
                record(entry)
    finally:
        bar.close()
    write_manifest(out, manifest(True))
    total = sum(int(e["bytes"]) for e in done.values()) + meta_bytes
    seconds = time.perf_counter() - t_start
    num_cams = len(ctx.converted)
    log.info("convert %s: %d shards (%d skipped), %d frames in %.1f s", out, len(tasks), skipped, frames_done, seconds)
    return ConvertResult(out, len(tasks), len(pending), skipped, frames_done, frames_done * num_cams, seconds, setup,
                         total)


def _is_complete_shard(path: Path, task: _Task) -> bool:
    from deliffas.data.shards import ShardFile

    reader = ShardFile(path)
    try:
        return int(reader.h5.attrs.get("complete", 0)) == 1 and list(reader.frames) == list(task.frames)
    except Exception:
        return False
    finally:
        reader.close()
