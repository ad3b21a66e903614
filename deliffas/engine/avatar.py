"""Self-contained runs and ``.avatar`` files: everything rendering needs, carried with the model.

A run writes ``RUN/capture.avatar`` when it starts training: the template spec and its source files,
atlas, faces, outer offsets, texel table, capture cameras and the identity of its shards
(:mod:`deliffas.engine.identity`), so ``render`` and ``view`` work after the shards and the subject
move or are deleted. ``export_avatar`` adds the model (config and weights) and writes one ``.avatar``
file (:mod:`deliffas.io.avatar_file`: safetensors + JSON, sha256 per array, no pickle).

Loading unpacks the template's source files into a cache folder (``$DELIFFAS_CACHE``, else
``$XDG_CACHE_HOME/deliffas``, else ``~/.cache/deliffas``) under their sha256, checks every file and
rebuilds the template through ``build_template`` as usual. The capture record is returned as a
``ShardMeta`` without frames, so the rendering code reads it as it reads a shard set's ``meta.h5``.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path, PurePosixPath

import numpy as np
import torch

from deliffas.data.shard_meta import ShardMeta
from deliffas.environment import cache_root  # where unpacked template files live (public here too)
from deliffas.data.shards import ShardSet, open_shard_set
from deliffas.engine.export_config import ExportConfig
from deliffas.engine.runs import load_run
from deliffas.engine.identity import capture_identity, recorded_shards
from deliffas.geometry.templates import TemplateSpec
from deliffas.io.avatar_file import AVATAR_SUFFIX, AvatarFileError, read_avatar_file, write_avatar_file
from deliffas.io.cameras import check_camera
from deliffas.io.infra.files import claim_output_file, sha256_file, write_bytes_atomic
from deliffas.models.deliffas import DeliffasModel, ModelConfig
from deliffas.models.unet import optimize_for_inference
from deliffas.models.checkpoint import config_from_dict, config_to_dict, load_checkpoint

__all__ = ["CAPTURE_FILE", "capture_record", "write_run_capture", "run_capture", "ExportConfig", "export_avatar",
           "load_avatar", "list_avatars", "cache_root"]

CAPTURE_FILE = "capture.avatar"
"""The run's capture record (an avatar file without weights), written when training starts."""
_META_ARRAYS = ("K", "world_to_cam", "sizes", "converted_cameras", "train_cameras", "test_cameras", "faces", "uvs",
                "face_uvs", "rest_verts", "outer_offsets", "texel_face", "texel_bary", "texel_valid")
_KEPT_ATTRS = ("subject", "capture_format", "character_sha256", "skinning", "offset_mm", "window", "atlas_res",
               "surface")
_FILE_PREFIX = "template_file/"
_MODEL_PREFIX = "model/"


def capture_record(meta: ShardMeta) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays and JSON record of a shard set's capture, with the template's source files embedded.

    Files are stored relative to their common folder so a ``.character`` finds the files it names.
    """
    spec = meta.template_spec()
    spec.verify()
    paths = {role: Path(os.path.abspath(p)) for role, p in spec.files.items()}  # the layout the spec read
    root = Path(os.path.commonpath([str(p.parent) for p in paths.values()])) if paths else Path(".")
    arrays = {name: np.asarray(getattr(meta, name)) for name in _META_ARRAYS}
    for role, p in paths.items():
        arrays[_FILE_PREFIX + role] = np.frombuffer(p.read_bytes(), np.uint8).copy()
    record = {"camera_names": list(meta.camera_names),
              "template": {"kind": spec.kind, "options": dict(spec.options), "sha256": dict(spec.sha256),
                           "files": {role: p.relative_to(root).as_posix() for role, p in paths.items()}},
              "attrs": {k: meta.attrs[k] for k in _KEPT_ATTRS if k in meta.attrs},
              "identity": capture_identity(meta)}
    return arrays, record


def write_run_capture(run_dir: str | os.PathLike, shards: ShardSet | str | os.PathLike) -> Path:
    """Write ``RUN/capture.avatar`` from the shards' ``meta.h5`` (atomic)."""
    arrays, record = capture_record(open_shard_set(shards).meta)
    return write_avatar_file(Path(run_dir) / CAPTURE_FILE, arrays, {"kind": "capture", **record})


def _unpack_template(where: Path, arrays: dict[str, np.ndarray], template: dict, cache: Path) -> TemplateSpec:
    """Write the embedded source files under ``cache/templates/<key>/`` (once) and return a spec naming them."""
    files, sums = template.get("files", {}), template.get("sha256", {})
    key = hashlib.sha256(json.dumps(sorted((r, files[r], sums.get(r)) for r in files)).encode()).hexdigest()[:24]
    folder = cache / "templates" / key
    out: dict[str, str] = {}
    for role, rel in files.items():
        parts = PurePosixPath(rel).parts
        if not parts or PurePosixPath(rel).is_absolute() or ".." in parts:
            raise AvatarFileError(f"{where}: template file {rel!r} ('{role}') is not a plain relative path")
        blob = arrays.get(_FILE_PREFIX + role)
        if blob is None:
            raise AvatarFileError(f"{where}: the template's '{role}' file is not embedded")
        if hashlib.sha256(blob.tobytes()).hexdigest() != sums.get(role):
            raise AvatarFileError(f"{where}: the embedded '{role}' file differs from its recorded sha256")
        target = folder.joinpath(*parts)
        if not target.is_file() or sha256_file(target) != sums[role]:
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                write_bytes_atomic(target, blob.tobytes())
            except OSError as err:
                raise PermissionError(f"{cache}: the template cache folder cannot be written ({err.strerror or err}); "
                                      "set $DELIFFAS_CACHE to a folder you can write") from None
        out[role] = str(target)
    return TemplateSpec(str(template.get("kind")), out, dict(sums), dict(template.get("options", {})))


def check_record_cameras(where: Path, arrays: dict[str, np.ndarray], names: list[str] | None = None) -> None:
    """Refuse a capture record whose cameras ``Camera`` would refuse (:func:`deliffas.io.cameras.check_camera`:
    shapes, a positive image size, K's and world_to_cam's last rows, focal lengths, principal point, rotation),
    before any work; ``names``: the record's camera names (else their indices).

    Raises:
        AvatarFileError: naming the file, the camera and what is wrong.
    """
    K, E, sizes = (np.asarray(arrays[n]) for n in ("K", "world_to_cam", "sizes"))
    if len(E) != len(K) or sizes.shape != (len(K), 2):
        raise AvatarFileError(f"{where}: camera arrays of shapes K {K.shape}, world_to_cam {E.shape}, sizes "
                              f"{sizes.shape}; expected (C, 3, 3), (C, 4, 4), (C, 2)")
    names = names if names is not None and len(names) == len(K) else [str(c) for c in range(len(K))]
    for c, name in enumerate(names):
        try:
            check_camera(name, K[c], E[c], int(sizes[c, 0]), int(sizes[c, 1]))
        except ValueError as err:
            raise AvatarFileError(f"{where}: {err}; the record is damaged (export the run again)") from None


def _meta_from(where: Path, arrays: dict[str, np.ndarray], record: dict, cache: Path) -> ShardMeta:
    missing = [n for n in _META_ARRAYS if n not in arrays]
    if missing or not isinstance(record.get("template"), dict):
        raise AvatarFileError(f"{where}: not a capture record (missing {missing or ['template']})")
    check_record_cameras(where, arrays, record.get("camera_names"))
    spec = _unpack_template(where, arrays, record["template"], cache)
    attrs = dict(record.get("attrs", {}), template_spec=spec.to_json())
    return ShardMeta(camera_names=list(record.get("camera_names", [])), sequence_frames={}, first_frames={},
                     attrs=attrs, **{n: arrays[n] for n in _META_ARRAYS})


def run_capture(run: str | os.PathLike, cache: Path | None = None) -> tuple[ShardMeta, dict]:
    """A run's capture record (as a ``ShardMeta`` without frames) and its identity.

    Reads ``RUN/capture.avatar``; a run trained before runs carried it falls back to its shards.
    """
    run = Path(run)
    path = run / CAPTURE_FILE
    if path.is_file():
        f = read_avatar_file(path)
        return _meta_from(path, f.arrays, f.record, cache or cache_root()), f.record.get("identity", {})
    record = _train_record(run)
    shards = recorded_shards(run, record)
    if shards is None:
        raise FileNotFoundError(f"{run}: no {CAPTURE_FILE} (a run from before runs carried their capture) and its "
                                f"shards {record.get('train', {}).get('shards') or '(none recorded)'} are gone")
    meta = ShardSet(shards).meta
    return meta, capture_identity(meta)


def _train_record(run: Path) -> dict:
    p = run / "train_config.json"
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: corrupted JSON ({exc})") from None


def export_avatar(config: ExportConfig) -> Path:
    """Write the run's model and capture as one ``.avatar`` file (refuses an existing ``out`` unless ``overwrite``)."""
    out_path = Path(config.out)
    if out_path.suffix != AVATAR_SUFFIX:
        raise ValueError(f"{out_path}: an avatar file must end in {AVATAR_SUFFIX}")
    claim_output_file(out_path, config.overwrite)
    run = Path(config.run)
    ckpt = load_checkpoint(run / "checkpoint")
    meta, _ = run_capture(run)
    arrays, record = capture_record(meta)
    for name, value in ckpt.model.state_dict().items():
        arrays[_MODEL_PREFIX + name] = value.detach().cpu().numpy()
    train = _train_record(run)
    record.update(kind="avatar", model=config_to_dict(ckpt.config), checkpoint_extra=ckpt.extra,
                  train={k: train.get("train", {}).get(k) for k in ("model", "preset", "iters", "seed")},
                  source_run=str(run.resolve()))
    return write_avatar_file(out_path, arrays, record)


def load_avatar(path: str | os.PathLike, device: str | torch.device = "cpu",
                cache: Path | None = None) -> tuple[DeliffasModel, dict, ShardMeta]:
    """The model (eval mode, inference forward), its record and capture, from a run folder or a ``.avatar`` file.

    The record has the shape of a run's ``train_config.json`` (``train``, ``model``, ``identity``).
    """
    p = Path(path)
    if p.is_dir():
        model, record = load_run(p, device)
        meta, identity = run_capture(p, cache)
        return model, dict(record, identity=record.get("identity") or identity), meta
    f = read_avatar_file(p)
    if f.record.get("kind") != "avatar" or not isinstance(f.record.get("model"), dict):
        raise AvatarFileError(f"{p}: holds no model (a run's {CAPTURE_FILE}? export the run with 'deliffas export')")
    config = config_from_dict(ModelConfig, f.record["model"], where=f"{p}: model")
    meta = _meta_from(p, f.arrays, f.record, cache or cache_root())
    if meta.atlas_res != config.atlas_res:
        raise AvatarFileError(f"{p}: the model's atlas side {config.atlas_res} differs from its capture's "
                              f"{meta.atlas_res} (texel table); the record is damaged (export the run again)")
    model = DeliffasModel(config)
    state = {k[len(_MODEL_PREFIX):]: torch.from_numpy(v.copy()) for k, v in f.arrays.items()
             if k.startswith(_MODEL_PREFIX)}
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise AvatarFileError(f"{p}: weights do not match its model config ({str(exc)[:200]})") from None
    record = {"train": dict(f.record.get("train", {})), "model": f.record["model"], "identity": f.record["identity"]}
    return optimize_for_inference(model.to(torch.device(device)).eval()), record, meta


def list_avatars(folder: str | os.PathLike) -> list[dict]:
    """Every ``.avatar`` file under ``folder`` (sorted): path, model, preset, atlas side, MB; or the error
    that makes it unreadable (each file is verified)."""
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a folder")
    rows = []
    for p in sorted(root.rglob(f"*{AVATAR_SUFFIX}")):
        if p.name == CAPTURE_FILE:
            continue
        try:
            f = read_avatar_file(p)
            if f.record.get("kind") != "avatar":
                raise AvatarFileError(f"{p}: holds no model")
            train = f.record.get("train", {})
            rows.append({"path": str(p), "model": train.get("model"), "preset": train.get("preset"),
                         "atlas_res": f.record.get("model", {}).get("atlas_res"), "mb": p.stat().st_size / 1e6,
                         "identity": f.record.get("identity")})
        except AvatarFileError as exc:
            rows.append({"path": str(p), "error": str(exc)})
    return rows
