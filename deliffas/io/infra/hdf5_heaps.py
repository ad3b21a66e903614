"""A check of an HDF5 file's global heap collections before libhdf5 reads them.

Variable-length strings and arrays (a DNA-Rendering camera's ``name`` attribute, for one) live in
global heap collections ("GCOL"). libhdf5 decodes a collection object by object, stepping by each
object's recorded size; a damaged size can land the next step on a zero header, which steps by 0,
and the library then loops forever inside ``H5Aread`` (libhdf5 2.0.0, the build h5py 3.16 ships;
found by the ``.smc`` soak, where one damaged byte made a camera-name read spin for hours). A
reader of foreign HDF5 files calls :func:`looping_global_heap` first and refuses such a file.

The scan follows the file format specification (version 1 collections, 8-byte lengths, objects
aligned to 8 bytes). A collection is recognised by its signature, version and zero reserved bytes,
and a minimum size; image bytes that happen to look like one are not decoded by libhdf5, and only a
layout that would not advance is reported, so a valid file is never refused in practice.
"""

from __future__ import annotations

import mmap
import os
import struct
from pathlib import Path

__all__ = ["looping_global_heap"]

_SIGNATURE = b"GCOL\x01\x00\x00\x00"  # signature, version 1, three reserved bytes
_HEADER = 16  # signature, version, reserved, collection size (8 bytes)
_OBJECT_HEADER = 16  # heap object index (2), reference count (2), reserved (4), object size (8)
_MIN_COLLECTION = 4096  # libhdf5 never writes a smaller collection (H5HG_MINSIZE)


def _collection_problem(buf, start: int, file_size: int) -> str | None:
    size = struct.unpack_from("<Q", buf, start + 8)[0]
    if size < _MIN_COLLECTION or start + size > file_size:
        return None  # not a collection libhdf5 would decode in full (it refuses a short one itself)
    p, end = start + _HEADER, start + size
    while p < end:
        if p + _OBJECT_HEADER > end:  # the tail is free space
            return None
        index = struct.unpack_from("<H", buf, p)[0]
        obj_size = struct.unpack_from("<Q", buf, p + 8)[0]
        step = _OBJECT_HEADER + (obj_size + 7) // 8 * 8 if index > 0 else obj_size  # object 0: free space
        if step == 0 or step > end - p:
            return (f"global heap collection at byte {start}: object {index} at byte {p} records size {obj_size}, "
                    f"which {'does not advance' if step == 0 else 'runs past the collection'}")
        p += step
    return None


def looping_global_heap(path: str | os.PathLike) -> str | None:
    """Why libhdf5 would loop forever (or read past a collection) decoding a global heap of ``path``, or None.

    Args:
        path: an HDF5 file, read whole through a memory map (about 0.7 s per GB from the page cache,
            on every call: ``SmcFile`` calls it at each open, so the DNA-Rendering parser opens each file
            once, and a conversion keeps one open per worker across its shards).

    Returns:
        A sentence naming the collection's and the object's byte offsets, or None when every
        collection decodes.
    """
    path = Path(path)
    file_size = path.stat().st_size
    if file_size < _HEADER:
        return None
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        at = buf.find(_SIGNATURE)
        while at >= 0:
            if at + _HEADER <= file_size:
                problem = _collection_problem(buf, at, file_size)
                if problem is not None:
                    return problem
            at = buf.find(_SIGNATURE, at + 1)
    return None
