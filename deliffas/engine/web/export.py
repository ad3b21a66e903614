"""``deliffas export RUN|AVATAR OUT --web``: a static folder that plays the avatar in a browser.

The folder holds ``index.html`` and the player's ES modules (``player/``, package data of this package),
``avatar.json`` (the model's and the scene's description and the index of every array) and ``avatar.bin`` (the
arrays: weights, mesh, atlas tables, motion). It is written into a temporary folder beside ``OUT`` and renamed
into place, so a crash leaves no half-written ``OUT``; an existing ``OUT`` is replaced only with ``overwrite``.
"""

from __future__ import annotations

import json
import os
import shutil
from importlib import resources
from pathlib import Path

from deliffas import __version__
from deliffas.engine.avatar import load_avatar
from deliffas.engine.render import find_motion
from deliffas.engine.export_config import ExportConfig
from deliffas.engine.web.bundle import Bundle
from deliffas.engine.web.model_pack import check_web_supported, pack_model
from deliffas.engine.web.scene_pack import pack_scene

__all__ = ["WEB_FORMAT", "PLAYER_FILES", "export_web", "player_files"]

WEB_FORMAT = {"format": "deliffas-web", "version": 1}
"""What ``avatar.json`` says it is."""

PLAYER_FILES = ("index.html", "player/main.js", "player/gl.js", "player/unet.js", "player/geometry.js",
                "player/raster.js", "player/shade.js", "player/orbit.js", "player/ui.js", "player/smpl.js",
                "player/backend.js", "player/webgl_backend.js", "player/cpu_backend.js", "player/cpu_unet.js",
                "player/cpu_raster.js", "player/cpu_shade.js")
"""The player's files, copied into every export (paths inside the export)."""


def player_files() -> dict[str, bytes]:
    """The player's files by their path in the export (package data: ``deliffas/engine/web/player``)."""
    root = resources.files("deliffas.engine.web") / "player"
    return {name: (root / Path(name).name).read_bytes() if name.startswith("player/")
            else (root / name).read_bytes() for name in PLAYER_FILES}


def _is_web_export(index: Path) -> bool:
    try:
        return json.loads(index.read_text()).get("format") == WEB_FORMAT["format"]
    except (OSError, ValueError, AttributeError):
        return False


def _claim(out: Path, overwrite: bool) -> None:
    """Refuse ``out`` unless it is new, an empty folder, or (with ``overwrite``) an earlier web export."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: is a file; --web writes a folder")
    if out.exists() and any(out.iterdir()):
        if not _is_web_export(out / "avatar.json"):
            raise FileExistsError(f"{out}: a folder that is not a web export of deliffas (no avatar.json of format "
                                  f"{WEB_FORMAT['format']!r}); choose another OUT")
        if not overwrite:
            raise FileExistsError(f"{out}: exists; pass --overwrite to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)


def _write_folder(tmp: Path, index: dict, bundle: Bundle) -> None:
    for name, data in player_files().items():
        (tmp / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp / name).write_bytes(data)
    (tmp / "avatar.bin").write_bytes(bundle.tobytes())
    (tmp / "avatar.json").write_text(json.dumps(index, indent=1))
    for p in tmp.rglob("*"):
        if p.is_file():
            with open(p, "rb") as f:
                os.fsync(f.fileno())


def _put_in_place(tmp: Path, out: Path) -> None:
    """Rename ``tmp`` to ``out``; an existing ``out`` is moved aside first and removed after."""
    old = out.with_name(f".{out.name}.old-{os.getpid()}")
    if out.exists():
        out.rename(old)
    tmp.rename(out)
    if old.exists():
        shutil.rmtree(old)


def export_web(config: ExportConfig) -> Path:
    """Write the avatar of ``config.run`` (a run folder or an ``.avatar`` file) as a web page folder ``config.out``.

    Raises:
        ValueError: the model's variant is one the player does not render (the message lists the supported ones).
        FileExistsError: ``out`` exists and ``overwrite`` is not set.
    """
    out = Path(config.out)
    _claim(out, config.overwrite)
    model, record, meta = load_avatar(config.run)
    check_web_supported(model.config)
    motion = find_motion(meta, config.motion)
    bundle = Bundle()
    index = {**WEB_FORMAT, "deliffas": __version__, "train": record.get("train", {}),
             "model": pack_model(model, bundle), "scene": pack_scene(meta, motion, config.frames, bundle)}
    index["arrays"] = bundle.entries
    index["bin_bytes"] = bundle.nbytes
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        _write_folder(tmp, index, bundle)
        _put_in_place(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return out
