"""The web export's arrays: one binary file of little-endian arrays and the JSON index that names them."""

from __future__ import annotations

import numpy as np

__all__ = ["Bundle", "BUNDLE_DTYPES"]

BUNDLE_DTYPES = {"float32": np.dtype("<f4"), "int32": np.dtype("<i4"), "uint8": np.dtype("u1")}
"""The dtypes a bundle stores, by the name its index gives (the player reads them as typed arrays)."""


class Bundle:
    """Arrays packed one after another into one byte string, each at a multiple of 4 bytes.

    ``add`` returns the array's entry of the index: ``{"offset", "shape", "dtype"}`` (offset in bytes), which
    the player turns into a typed array view of the fetched file.
    """

    def __init__(self) -> None:
        self._parts: list[bytes] = []
        self._size = 0
        self.entries: dict[str, dict] = {}

    def add(self, name: str, array, dtype: str = "float32") -> dict:
        """Append ``array`` converted to ``dtype`` (a key of :data:`BUNDLE_DTYPES`) under ``name``."""
        if name in self.entries:
            raise ValueError(f"bundle: {name!r} added twice")
        data = np.ascontiguousarray(np.asarray(array), BUNDLE_DTYPES[dtype])
        entry = {"offset": self._size, "shape": list(data.shape), "dtype": dtype}
        raw = data.tobytes()
        pad = (-len(raw)) % 4
        self._parts.append(raw + b"\0" * pad)
        self._size += len(raw) + pad
        self.entries[name] = entry
        return entry

    def tobytes(self) -> bytes:
        """The binary file's content."""
        return b"".join(self._parts)

    @property
    def nbytes(self) -> int:
        """Size of the binary file in bytes."""
        return self._size
