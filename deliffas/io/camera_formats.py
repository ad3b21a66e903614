"""One entry point to read and write cameras in every registered capture format, as deliffas ``Camera`` lists.

``read_cameras(path, fmt="auto")`` detects the format from the path (``detect_camera_format``) and
returns cameras in the deliffas convention (mm, world -> camera, OpenCV axes, pixel centres at +0.5,
OpenCV distortion in ``Camera.extra["distortion"]``); ``write_cameras(cameras, out, fmt)`` writes them.
Each format converts at its own boundary (its module under ``deliffas.io.formats``, through
``deliffas.io.camera_conventions``) and registers a ``CaptureFormat``; this module only looks the format
up in the registry. :func:`convert_cameras` is what ``deliffas cameras SRC OUT --to FMT [--from FMT]`` calls.
:func:`camera_format_table` lists the formats: where each keeps its cameras, the lens terms it
holds, whether it records the image size.

Writers refuse (``LossyConversionError``) a camera whose lens distortion the target cannot hold
unless ``drop_distortion=True``, which logs a warning per camera.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from deliffas.io.camera_config import CamerasConfig
from deliffas.io.camera_conventions import LossyConversionError
from deliffas.io.cameras import Camera, check_camera_names
from deliffas.io.format_registry import CameraWriteOptions, capture_format, capture_formats
from deliffas.io.infra.reader_checks import require_unique_names

__all__ = ["camera_format_names", "camera_format_table", "detect_camera_format", "read_cameras", "write_cameras",
           "CamerasConfig", "CameraConversion", "convert_cameras", "shorthand_fields"]

PathLike = str | os.PathLike


def camera_format_names() -> tuple[str, ...]:
    """Every ``fmt`` that ``read_cameras`` and ``write_cameras`` accept, in detection order."""
    return tuple(f.name for f in capture_formats("read_cameras", "write_cameras"))


def camera_format_table() -> str:
    """A Markdown table of the camera formats: name, what is read/written, lens terms held, image size stored."""
    rows = ["| fmt | format | cameras in | lens terms held | image size |", "|---|---|---|---|---|"]
    for f in capture_formats("read_cameras"):
        where = "the folder" if f.camera_path == "." else f"`{f.camera_path}`"
        lens = ", ".join(f.distortion) if f.distortion else "none"
        rows.append(f"| `{f.name}` | {f.title} | {where} | {lens} | {'stored' if f.stores_size else 'from the images, or --size'} |")
    return "\n".join(rows)


def detect_camera_format(path: PathLike, hint: str = "fmt=") -> str:
    """The camera format of ``path`` (a file, or a folder holding one): the first registered format whose
    ``detect_cameras`` accepts it. ``hint``: how the message tells to name the format (a CLI: ``--from FORMAT``).

    Raises:
        ValueError: nothing recognisable, naming the formats tried.
    """
    p = Path(path)
    formats = capture_formats("detect_cameras")
    for f in formats:
        if f.detect_cameras(p):
            return f.name
    names = ", ".join(f.name for f in formats)
    if p.is_dir():
        raise ValueError(f"{p}: no camera file found (looked for {names}); pass {hint}")
    raise ValueError(f"{p}: cannot tell the camera format from the name; pass {hint} (one of {names})")


def read_cameras(path: PathLike, fmt: str = "auto", size: tuple[int, int] | None = None) -> list[Camera]:
    """Read the cameras of ``path`` as deliffas Cameras.

    Args:
        fmt: a registered camera format (``camera_format_names()``), or "auto" (``detect_camera_format``).
        size: (width, height) for formats or files that store no image size (``camera_format_table``);
            ignored where the file has it.

    Raises:
        CaptureFormatError: a malformed file (each reader names the file and key), an implausible camera
            (``check_camera``) or a camera name given twice.
        ValueError: an unknown format, or a required ``size`` missing.
    """
    name = detect_camera_format(path) if fmt == "auto" else fmt
    cameras = capture_format(name, "read_cameras", what="camera").read_cameras(Path(path), size)
    require_unique_names(path, "camera names", [c.name for c in cameras])  # every format, plug-ins included
    return cameras


def write_cameras(cameras: Sequence[Camera], out: PathLike, fmt: str, drop_distortion: bool = False,
                  text: bool = False) -> Path:
    """Write ``cameras`` in ``fmt``; returns the file (or folder) written.

    ``out`` is the file to write, or an existing folder, which gets the format's usual name
    (``CaptureFormat.camera_path``: ``annots.npy``, ``transforms.json``, ...; formats whose cameras are a
    folder, COLMAP and EasyMocap, write into ``out``). ``text``: the format's text variant
    (``CaptureFormat.text_variant``, e.g. COLMAP's .txt model instead of .bin).

    Raises:
        LossyConversionError: distortion the format cannot hold (unless ``drop_distortion``).
        ValueError: an unknown format, ``text`` for a format without a text variant, a camera the format cannot
            represent (e.g. skew), or a camera name given twice.
    """
    f = capture_format(fmt, "write_cameras", what="camera")
    if text and f.text_variant is None:
        having = ", ".join(g.name for g in capture_formats("text_variant", "write_cameras")) or "none"
        raise ValueError(f"text: {fmt} has no text variant (formats with one: {having})")
    cameras = list(cameras)
    if not cameras:
        raise ValueError("write_cameras: no cameras to write")
    check_camera_names([c.name for c in cameras], f"{out}")  # one file or entry per name
    out_p = Path(out)
    if out_p.is_dir() and f.camera_path not in (None, "."):
        out_p = out_p / f.camera_path
    return f.write_cameras(cameras, out_p, CameraWriteOptions(drop_distortion=drop_distortion, text=text))


@dataclass(frozen=True)
class CameraConversion:
    """What :func:`convert_cameras` wrote."""

    count: int
    fmt: str
    path: Path


def shorthand_fields() -> dict[str, tuple[str, str]]:
    """The ``CamerasConfig`` field of each format shorthand (``CaptureFormat.shorthand_with``), as
    ``{field: (direction, format)}``: ``to_NAME`` -> ("to", NAME), ``from_NAME`` -> ("from", NAME)."""
    return {f"{d}_{f.name}": (d, f.name) for f in capture_formats("shorthand_with") for d in ("to", "from")}


def _conversion_ends(config: CamerasConfig) -> tuple[Path, str, Path, str]:
    """(source, its format, output, its format) with the format shorthands (``--to-NAME DIR``) resolved."""
    fields = shorthand_fields()
    flag = lambda key: "--" + key.replace("_", "-")  # noqa: E731
    given = [(key, getattr(config, key)) for key in fields if getattr(config, key, None) is not None]
    if not given:
        if config.out is None or config.to_format is None:
            raise ValueError(f"give OUT and --to FORMAT (or {' / '.join(flag(k) + ' DIR' for k in fields)})")
        return Path(config.src), config.from_format, Path(config.out), config.to_format
    if len(given) > 1:
        raise ValueError(f"give {' or '.join(flag(k) for k, _ in given)}, not both")
    if config.out is not None or config.to_format is not None:
        raise ValueError(f"{flag(given[0][0])} takes no OUT and no --to")
    (key, folder), = given
    direction, name = fields[key]
    if direction == "to":
        return Path(config.src), config.from_format, Path(folder), name
    return Path(folder), name, Path(config.src), str(capture_format(name).shorthand_with)


def convert_cameras(config: CamerasConfig, names: dict[str, str] | None = None) -> CameraConversion:
    """Read the cameras of ``config.src`` and write them in ``config.to_format`` (each field: :class:`CamerasConfig`).

    ``names``: how to name a config field in a message (a CLI passes its flags, ``drop_distortion`` ->
    ``--drop-distortion``); without it the Python argument is named (``drop_distortion=True``).

    Raises:
        FileExistsError: OUT exists (other than an empty folder) and not ``config.overwrite``.
        LossyConversionError: as :func:`write_cameras`, naming ``names["drop_distortion"]``.
        ValueError: OUT / ``--to`` missing, or given with a format shorthand (``shorthand_fields``); as :func:`read_cameras` and
            :func:`write_cameras`.
    """
    src, src_format, out, to = _conversion_ends(config)
    if out.exists() and not config.overwrite and not (out.is_dir() and not any(out.iterdir())):
        raise FileExistsError(f"{out} exists; pass --overwrite to replace it")
    if src_format == "auto" and names is not None and "from_format" in names:
        src_format = detect_camera_format(src, hint=f"{names['from_format']} FORMAT")
    cameras = read_cameras(src, src_format, config.size)
    try:
        written = write_cameras(cameras, out, to, drop_distortion=config.drop_distortion, text=config.text)
    except LossyConversionError as err:
        if names is None or "drop_distortion" not in names:
            raise
        raise err.naming(names["drop_distortion"]) from err
    return CameraConversion(len(cameras), to, written)
