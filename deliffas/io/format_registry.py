"""The capture-format plug-in: one :class:`CaptureFormat` record per format, registered by name.

Everything that lists formats (``read_cameras``/``write_cameras``, ``parse_subject``, ``export_capture``,
the command line) iterates :func:`capture_formats`; nothing else names a format. A format is
registered in parts, each by the layer that can write it: its module under ``deliffas/io/formats/``
registers the cameras (detect, read, write), its module under ``deliffas/data/subjects/`` the
subject parser and the export (the io layer may not import ``data``). Registering merges the parts
of one name into one record and refuses a capability given twice; a capability a format lacks stays
``None``.

The built-in formats' camera parts are registered by ``deliffas.io.formats.builtin`` (one line each,
each module defining its ``FORMAT``); installed packages add formats through the ``deliffas.formats``
entry-point group (see :func:`deliffas.plugins.load_plugins`), loaded on the first lookup.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from deliffas.io.cameras import Camera
from deliffas.plugins import load_plugins

__all__ = ["CaptureFormat", "CameraWriteOptions", "register_capture_format", "capture_formats", "capture_format",
           "FORMATS_ENTRY_POINT"]

FORMATS_ENTRY_POINT = "deliffas.formats"
"""The entry-point group whose modules register capture formats when imported."""

PathLike = str | os.PathLike


@dataclass(frozen=True)
class CameraWriteOptions:
    """How ``write_cameras`` writes.

    Attributes:
        drop_distortion: zero the lens terms the format cannot hold (logged per camera) instead of refusing.
        text: the format's text variant (``CaptureFormat.text_variant``; refused where it has none).
    """

    drop_distortion: bool = False
    text: bool = False


@dataclass(frozen=True)
class CaptureFormat:
    """One capture format and what deliffas does with it; a capability the format lacks is ``None``.

    Attributes:
        name: the name users type (``--from``/``--to``/``--format``).
        title: the format as people call it (help text, docs).
        camera_path: where a capture of this format keeps its cameras, relative to its folder: what
            ``write_cameras`` writes when given that folder (``.``: the folder itself is the model).
        distortion: the OpenCV lens coefficients its camera file holds (names of
            ``camera_conventions.DISTORTION_NAMES``; ``()`` for none).
        stores_size: whether its camera file records the image size (else readers need ``size=``).
        text_variant: what ``CameraWriteOptions.text`` writes instead of the usual file (e.g. COLMAP's ``.txt``
            model); None: the format has no text variant, and ``text`` is refused.
        shorthand_with: ``deliffas cameras`` spells ``SRC --to NAME DIR`` as ``SRC --to-NAME DIR`` and
            ``DIR --to FORMAT SRC`` as ``SRC --from-NAME DIR``, FORMAT being this field (the format such a
            SRC is in); None: no such shorthand. The command's config declares one field per shorthand
            (``to_NAME``, ``from_NAME``).
        detect_cameras: ``(path) -> bool``: ``path`` (a camera file, or a folder holding one) is this format's.
        read_cameras: ``(path, size) -> list[Camera]`` in the deliffas convention; ``size`` (W, H) or None.
        write_cameras: ``(cameras, out, CameraWriteOptions) -> Path``: the file or folder written.
        detect_subject: ``(folder) -> bool``: the folder is a capture of this format (data layer).
        parse_subject: ``(folder, SubjectOptions) -> Subject`` (data layer).
        export: ``(ExportFrames, out_folder, jpeg_quality) -> None``: write a sequence in this layout (data layer).
    """

    name: str
    title: str = ""
    camera_path: str | None = None
    distortion: tuple[str, ...] | None = None
    stores_size: bool | None = None
    text_variant: str | None = None
    shorthand_with: str | None = None
    detect_cameras: Callable[[Path], bool] | None = None
    read_cameras: Callable[[Path, tuple[int, int] | None], list[Camera]] | None = None
    write_cameras: Callable[[Sequence[Camera], Path, CameraWriteOptions], Path] | None = None
    detect_subject: Callable[[Path], bool] | None = None
    parse_subject: Callable[[Path, Any], Any] | None = None
    export: Callable[[Any, Path, int], None] | None = None


_FORMATS: dict[str, CaptureFormat] = {}
_BUILTINS_LOADED = False


def register_capture_format(part: CaptureFormat) -> CaptureFormat:
    """Register ``part`` (the capabilities one layer gives a format) and return the format's merged record.

    The built-in formats are registered first (``deliffas.io.formats.builtin``), so their order does not
    depend on which module was imported first.

    Raises:
        ValueError: a capability (or fact) of ``part.name`` that is registered already.
    """
    _load_builtins()
    old = _FORMATS.get(part.name)
    if old is None:
        _FORMATS[part.name] = part
        return part
    given = {f.name: getattr(part, f.name) for f in fields(part) if f.name != "name"}
    given = {k: v for k, v in given.items() if v is not None and v != ""}
    twice = [k for k in given if getattr(old, k) not in (None, "")]
    if twice:
        raise ValueError(f"capture format {part.name!r}: {', '.join(twice)} registered already")
    merged = replace(old, **given)
    _FORMATS[part.name] = merged
    return merged


def _load_builtins() -> None:
    global _BUILTINS_LOADED
    if not _BUILTINS_LOADED:
        _BUILTINS_LOADED = True
        import deliffas.io.formats.builtin  # noqa: F401  # local: import cycle (registers the built-in formats; it imports this module)


def capture_formats(*capabilities: str) -> tuple[CaptureFormat, ...]:
    """The registered formats having every named capability (e.g. ``"read_cameras"``), in registration order."""
    _load_builtins()
    load_plugins(FORMATS_ENTRY_POINT)
    return tuple(f for f in _FORMATS.values() if all(getattr(f, c) is not None for c in capabilities))


def capture_format(name: str, *capabilities: str, what: str = "capture") -> CaptureFormat:
    """The format ``name``, which must have every named capability.

    Args:
        what: the word for the format in the error (``"camera"``: ``unknown camera format 'x'``).

    Raises:
        ValueError: an unknown name, or one lacking a capability; the message lists the formats that have it.
    """
    having = capture_formats(*capabilities)
    for f in having:
        if f.name == name:
            return f
    expected = f"expected one of {', '.join(f.name for f in having)}"
    if name in _FORMATS:
        lacking = ", ".join(c for c in capabilities if getattr(_FORMATS[name], c) is None)
        raise ValueError(f"{what} format {name!r} has no {lacking}; {expected}")
    raise ValueError(f"unknown {what} format {name!r}; {expected}")
