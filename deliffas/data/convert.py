"""Conversion of a capture (a ``Subject``) into sharded HDF5 (docs/shards.md).

``convert(subject, out_dir, ConvertConfig)`` plans shards of consecutive selected frames per
sequence, writes ``meta.h5``, converts the shards (one task per shard, handed to the executor of
:func:`deliffas.parallel.open_executor`: in-process, spawned worker processes or a Dask cluster; see
:mod:`deliffas.data.shard_build`), checks each returned checksum against the file and rewrites
``manifest.json`` atomically after every finished shard. ``resume`` keeps the shards the manifest lists whose checksum still matches, and re-adds
shards that reached their final name before the manifest was updated. The capture is only read.

Per frame the surface is the posed template (``build_template(subject.template).pose`` of the
sequence's pose parameters), or a tracked ``.meshes`` sequence; the outer surface is the inner one
moved by d (30 mm, or per vertex from a variant's ``outer.obj``) along the vertex normals.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from deliffas.io.infra.files import TMP_MARK, sha256_file
from deliffas.data.shard_build import ShardBuilder, ShardSettings, ShardTask
from deliffas.data.shard_meta import ShardMeta, write_meta
from deliffas.data.shards import (
    MANIFEST_NAME,
    META_NAME,
    SCHEMA_VERSION,
    SHARD_DIR,
    Codec,
    ShardFile,
    read_manifest,
    write_manifest,
)
from deliffas.data.convert_config import ConvertConfig
from deliffas.data.subjects import Subject, parse_subject
from deliffas.data.synth_config import check_synth_images
from deliffas.data.check import check_before_convert
from deliffas.geometry.shell import mesh_edges
from deliffas.parallel import TaskExecutor, open_executor

__all__ = ["ConvertConfig", "ConvertResult", "convert", "parse_frame_range"]

log = logging.getLogger(__name__)


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


# --------------------------------------------------------------------------------------------- planning
@dataclass(frozen=True)
class _Plan:
    """The selected frames per sequence, the shard tasks and the camera split of one conversion."""
    frames: dict[str, np.ndarray]
    tasks: list[ShardTask]
    cameras: tuple[int, ...]
    train: list[int]
    test: list[int]


def _plan(subject: Subject, config: ConvertConfig) -> _Plan:
    num_cameras = len(subject.cameras)
    if config.cameras is not None:
        converted = sorted({int(c) for c in config.cameras})
        if not converted or converted[0] < 0 or converted[-1] >= num_cameras:
            raise ValueError(f"--cameras {list(config.cameras)}: indices must be in [0, {num_cameras})")
    else:
        converted = list(range(num_cameras))
    sl = parse_frame_range(config.frames)
    frames: dict[str, np.ndarray] = {}
    tasks: list[ShardTask] = []
    for name, seq in subject.sequences.items():
        selected = _select(seq.frames, sl)
        have = seq.images.image_frames()
        if have is not None:
            missing = [int(f) for f in selected if int(f) not in have]
            if missing:
                log.warning("%s: %d selected frames have no image folder (first %d); skipped", name, len(missing),
                            missing[0])
                selected = np.array([f for f in selected if int(f) in have], np.int64)
        if len(selected) == 0:
            raise ValueError(f"{name}: no frames selected by --frames {config.frames!r}")
        frames[name] = selected
        for k in range(0, len(selected), config.shard_frames):
            fr = selected[k: k + config.shard_frames]
            geo = np.unique(np.maximum(fr[:, None] - np.arange(config.window + 1)[None], seq.first_frame))
            tasks.append(ShardTask(f"{SHARD_DIR}/{name}-{k // config.shard_frames:05d}.h5", name,
                                   tuple(int(f) for f in fr), tuple(int(f) for f in geo)))
    test = [c for c in subject.test_cameras if c in converted]
    train = [c for c in converted if c not in test]
    return _Plan(frames, tasks, tuple(converted), train, test)


def _manifest_config(subject: Subject, config: ConvertConfig) -> dict:
    keep = {k: v for k, v in asdict(config).items()
            if k not in ("jobs", "dask", "resume", "overwrite", "progress", "check")}
    keep["format"] = subject.format
    keep["subject"] = str(subject.root)
    keep["character"] = subject.template.files.get("character", "")
    keep["template_spec"] = subject.template.to_dict()
    return json.loads(json.dumps(keep))  # tuples -> lists, as read back from JSON


def _sources_hash(subject: Subject) -> str:
    """One sha256 over the template's source files (changes when any of them does)."""
    h = hashlib.sha256()
    for role in sorted(subject.template.sha256):
        h.update(f"{role}\0{subject.template.sha256[role]}\0".encode())
    return h.hexdigest()


# --------------------------------------------------------------------------------------------- main entry
def _warn_if_not_watertight(where: str, faces: np.ndarray) -> None:
    """Log where a template has holes: rays through them see no inner surface (the outer exit is used)."""
    edges, counts, _ = mesh_edges(np.asarray(faces, np.int64))
    boundary = np.unique(edges[counts == 1])
    if len(boundary) or np.any(counts > 2):
        log.warning("%s: the template is not watertight: %d boundary vertices (first ids %s), %d non-manifold edges",
                    where, len(boundary), boundary[:10].tolist(), int(np.sum(counts > 2)))


def _build_meta(subject: Subject, plan: _Plan, builder: ShardBuilder, config: ConvertConfig) -> ShardMeta:
    first = next(iter(subject.sequences.values()))
    w, h = first.width, first.height
    scaled = [c.rescaled(w, h) if (c.width, c.height) != (w, h) else c for c in subject.cameras]
    template = builder.template
    faces = template.faces.numpy()
    spec = subject.template
    _warn_if_not_watertight(spec.files.get("character", spec.kind), faces)
    table = builder.table
    attrs = {
        "subject": str(subject.root), "capture_format": subject.format,
        "character_path": spec.files.get("character", ""), "character": spec.files.get("character", ""),
        "character_sha256": _sources_hash(subject), "template_spec": spec.to_json(),
        "outer_obj": spec.files.get("outer", ""),
        "surface": "meshes" if config.meshes else ("variant" if config.template else "template"),
        "meshes": json.dumps(list(config.meshes)), "skinning": spec.option("skinning", config.skinning),
        "offset_mm": float(config.offset_mm), "codec": Codec.parse(config.codec).spec, "window": int(config.window),
        "atlas_res": int(config.atlas_res), "gutter": int(config.gutter), "shard_frames": int(config.shard_frames),
    }
    return ShardMeta(
        camera_names=[c.name for c in scaled], K=np.stack([c.K for c in scaled]),
        world_to_cam=np.stack([c.world_to_cam for c in scaled]),
        sizes=np.array([[c.width, c.height] for c in scaled], np.int64),
        converted_cameras=np.asarray(plan.cameras, np.int64), train_cameras=np.asarray(plan.train, np.int64),
        test_cameras=np.asarray(plan.test, np.int64), sequence_frames=dict(plan.frames),
        first_frames={k: s.first_frame for k, s in subject.sequences.items()},
        faces=faces, uvs=template.uvs.numpy(), face_uvs=template.face_uvs.numpy(),
        rest_verts=template.rest_verts.numpy(), outer_offsets=builder.offsets,
        texel_face=table.face.astype(np.int32), texel_bary=table.bary, texel_valid=table.valid, attrs=attrs)


def convert(subject: Subject | str | os.PathLike, out_dir: str | os.PathLike,
            config: ConvertConfig = ConvertConfig()) -> ConvertResult:
    """Convert a capture into shards + ``meta.h5`` + ``manifest.json`` under ``out_dir``.

    Args:
        subject: a parsed :class:`Subject`, or a capture folder (parsed with ``config.format`` and
            ``config.subject_options()``).
    """
    t_start = time.perf_counter()
    out = Path(out_dir).resolve()
    if config.shard_frames < 1 or config.window < 0 or config.atlas_res < 4:
        raise ValueError("shard_frames >= 1, window >= 0 and atlas_res >= 4 are required")
    Codec.parse(config.codec)
    if not (out / MANIFEST_NAME).is_file() and out.is_dir() and any(out.iterdir()) and not config.overwrite:
        if not _is_partial_start(out):
            raise FileExistsError(f"{out}: not empty and holds no conversion; pass --overwrite to convert into it")
        if not config.resume:  # a conversion killed before its first manifest: nothing of the user's is here
            raise FileExistsError(f"{out}: holds the start of an interrupted conversion (no manifest yet); "
                                  "use --resume or --overwrite")
    if not isinstance(subject, Subject):
        root = Path(subject).resolve()
        if out == root or root in out.parents:
            raise ValueError(f"output {out} lies inside the source folder {root}; the source is never written to")
        subject = parse_subject(root, config.format, config.subject_options())
    if out == subject.root or subject.root in out.parents:
        raise ValueError(f"output {out} lies inside the source folder {subject.root}; the source is never written to")
    check_synth_images(subject.root)
    if config.check:
        check_before_convert(subject)
    plan = _plan(subject, config)
    # the executor connects (or starts its workers) before anything is written: an unreachable
    # Dask scheduler is an error that leaves OUT as it was
    with open_executor(config.jobs, config.dask) as executor:
        return _convert_planned(subject, out, config, plan, executor, t_start)


def _convert_planned(subject: Subject, out: Path, config: ConvertConfig, plan: _Plan, executor: TaskExecutor,
                     t_start: float) -> ConvertResult:
    tasks = plan.tasks
    mconfig = _manifest_config(subject, config)
    old = _previous_manifest(out, config, mconfig)
    (out / SHARD_DIR).mkdir(parents=True, exist_ok=True)
    _remove_leftovers(out)

    settings = ShardSettings(out, plan.cameras, config.atlas_res, config.gutter, config.offset_mm, config.window,
                             config.codec)
    builder = ShardBuilder.create(subject, settings)
    meta = _build_meta(subject, plan, builder, config)
    meta_sha, meta_bytes = write_meta(out / META_NAME, meta)
    done = _resumable_shards(out, tasks, old) if old is not None else {}
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
        _check_returned(out, entry)
        done[entry["name"]] = entry
        frames_done += len(entry["frames"])
        write_manifest(out, manifest(False))
        bar.update(1)
        bar.set_postfix(frames_s=f"{frames_done / max(time.perf_counter() - t_start, 1e-9):.2f}")

    try:
        # the subject (with its pose parameters) goes to each worker once, in the setup; tasks stay small
        for entry in executor.map(ShardBuilder.write, [(t,) for t in pending], ShardBuilder.create,
                                  (subject, settings), local_state=builder):
            record(entry)
    finally:
        bar.close()
        builder.close()
    _remove_leftovers(out)  # temporary files of attempts killed with their worker (retried elsewhere)
    write_manifest(out, manifest(True))
    total = sum(int(e["bytes"]) for e in done.values()) + meta_bytes
    seconds = time.perf_counter() - t_start
    num_cams = len(plan.cameras)
    log.info("convert %s: %d shards (%d skipped), %d frames in %.1f s", out, len(tasks), skipped, frames_done, seconds)
    return ConvertResult(out, len(tasks), len(pending), skipped, frames_done, frames_done * num_cams, seconds, setup,
                         total)


def _previous_manifest(out: Path, config: ConvertConfig, mconfig: dict) -> dict | None:
    """The manifest of the conversion ``--resume`` continues (None: a fresh one; ``--overwrite`` removes it)."""
    if not (out / MANIFEST_NAME).is_file():
        return None
    if config.overwrite:
        shutil.rmtree(out / SHARD_DIR, ignore_errors=True)
        (out / MANIFEST_NAME).unlink()
        (out / META_NAME).unlink(missing_ok=True)
        return None
    if not config.resume:
        raise FileExistsError(f"{out}: holds a conversion already; use --resume or --overwrite")
    old = read_manifest(out)
    if old.get("config") != mconfig:
        diff = sorted(k for k in set(mconfig) | set(old.get("config", {}))
                      if mconfig.get(k) != old.get("config", {}).get(k))
        raise ValueError(f"{out}: --resume with a different configuration (differs in {diff})")
    return old


def _resumable_shards(out: Path, tasks: list[ShardTask], old: dict) -> dict[str, dict]:
    """The manifest entries of the shards a resumed conversion keeps: listed with their sha256, or complete
    shards renamed before the manifest update."""
    done: dict[str, dict] = {}
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
    return done


def _is_partial_start(out: Path) -> bool:
    """``out`` holds only what a conversion writes before its first manifest: the shard folder (empty or with
    temporary files), ``meta.h5`` and temporary files; ``--resume`` starts such a conversion afresh."""
    for p in out.iterdir():
        if p.name == SHARD_DIR and p.is_dir() and not p.is_symlink():
            if any(TMP_MARK not in q.name or not q.name.startswith(".") for q in p.iterdir()):
                return False
        elif not (p.name == META_NAME and p.is_file() or p.name.startswith(".") and TMP_MARK in p.name):
            return False
    return True


def _remove_leftovers(out: Path) -> None:
    """Delete temporary files of killed writers (``.<name>.tmp-<pid>``) in ``out`` and its shard folder."""
    for leftover in list((out / SHARD_DIR).glob(f".*{TMP_MARK}*")) + list(out.glob(f".*{TMP_MARK}*")):
        log.info("removing leftover temporary file %s", leftover.name)
        leftover.unlink(missing_ok=True)


def _check_returned(out: Path, entry: dict) -> None:
    """The shard a worker reports must be here with the checksum it reported (OUT on a shared file system)."""
    path = out / entry["name"]
    if not path.is_file():
        raise FileNotFoundError(f"{path}: a worker reported this shard written but it is not here; OUT must be on a "
                                f"file system every worker shares, at the same path")
    sha = sha256_file(path)
    if sha != entry["sha256"]:
        raise ValueError(f"{path}: sha256 {sha[:12]}... differs from the {entry['sha256'][:12]}... its worker "
                         f"reported (was it written twice, or is OUT not shared?)")


def _is_complete_shard(path: Path, task: ShardTask) -> bool:
    reader = ShardFile(path)
    try:
        return int(reader.h5.attrs.get("complete", 0)) == 1 and list(reader.frames) == list(task.frames)
    except Exception:
        return False
    finally:
        reader.close()
