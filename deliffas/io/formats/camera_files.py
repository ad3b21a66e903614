"""What every format's camera reader and writer shares: detection by file name, the size a file lacks, named conversion."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

from deliffas.io.cameras import Camera
from deliffas.io.infra.reader_checks import naming_file

__all__ = ["file_detector", "in_folder", "need_size", "converted"]


def file_detector(*names: str, suffixes: tuple[str, ...] = (),
                  accept: Callable[[Path], bool] | None = None) -> Callable[[Path], bool]:
    """A ``detect_cameras``: a file named one of ``names`` or ending in one of ``suffixes``, or a folder
    holding one of ``names``; ``accept(file)`` (e.g. a look at its content) must also hold when given."""
    def detect(path: Path) -> bool:
        p = Path(path)
        if p.is_dir():
            return any((p / n).is_file() and (accept is None or accept(p / n)) for n in names)
        named = p.name in names or any(p.name.endswith(s) for s in suffixes)
        return named and p.is_file() and (accept is None or accept(p))
    return detect


def in_folder(path: Path, name: str) -> Path:
    """``path / name`` when ``path`` is a folder, else ``path``."""
    p = Path(path)
    return p / name if p.is_dir() else p


def need_size(fmt: str, size: tuple[int, int] | None, images: Path | None = None,
              camera: str = "") -> tuple[int, int]:
    """``size`` (width, height, ``--size``) for a format whose file stores none; without it, the size of the
    camera's first image (``images``: that file, or the folder of its numbered images).

    Raises:
        ValueError: ``size`` not positive, or missing with no image to read it from, saying to pass ``--size``.
    """
    if size is None:
        from deliffas.io.formats.capture_frames import image_file_size, numbered_files  # local: import cycle (it imports this module)

        files = {} if images is None else {0: images} if images.is_file() else numbered_files(images)
        if not files:
            where = f" and {images} holds no image to read it from" if images is not None else ""
            who = f"{fmt} camera {camera}" if camera else f"{fmt} cameras"
            raise ValueError(f"{who}: the file stores no image size{where}; pass --size WxH")
        return image_file_size(files[min(files)])
    w, h = (int(v) for v in size)
    if w <= 0 or h <= 0:
        raise ValueError(f"{fmt} cameras: --size must be positive, got {size}")
    return w, h


def converted(path: Path, records: Sequence, convert: Callable) -> list[Camera]:
    """``convert`` of each record (with a ``name``), a refused value (singular K, a translation that overflows
    in mm) named with the file and the camera."""
    out = []
    for r in records:
        with naming_file(path, f"camera {r.name}"):
            out.append(convert(r))
    return out
