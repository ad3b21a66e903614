"""Peak resident memory of a call, and the stated peak-memory bounds of rendering and training.

The bounds (docs/reliability.md, "Memory bounds") are what chunking guarantees: rendering grows
with the chunk, not with the shaded rays of a frame, and so does a training step with a
``ray_chunk``. They are checked by ``tests/reliability/test_resource_bounds.py`` and, for a
940 x 1285 frame, by ``make bench`` (group ``e2e``).

Measuring: ``peak_rss_growth`` resets the kernel's peak resident set (``/proc/self/clear_refs``,
Linux) and reports its growth over the resident set before the call. Run it in a fresh process
with ``MALLOC_MMAP_THRESHOLD_=65536`` so that glibc returns freed blocks to the system and every
call starts from a clean baseline (``PEAK_PROBE_ENV``).
"""

from __future__ import annotations

import ctypes
import gc
import sys
from pathlib import Path
from typing import Callable, TypeVar

__all__ = [
    "KIB",
    "MIB",
    "SLACK",
    "RENDER_BYTES_PER_PIXEL",
    "RENDER_BYTES_PER_CHUNK_RAY",
    "RENDER_BYTES_PER_RAY",
    "TRAIN_BYTES_PER_TEXEL",
    "TRAIN_BYTES_PER_CHUNK_RAY",
    "TRAIN_BYTES_PER_RAY",
    "TRAIN_BYTES_PER_PIXEL",
    "PEAK_PROBE_ENV",
    "frame_features_bytes",
    "render_peak_bound",
    "train_peak_bound",
    "peak_rss_growth",
    "retain_freed_memory",
]

KIB, MIB = 1024, 1024 * 1024
SLACK = 16 * MIB
"""Interpreter, allocator and page-granularity noise allowed on every bound."""
RENDER_BYTES_PER_PIXEL = 320
"""Ray casting per image pixel (float64 rays and the hits of the inner/outer/exit surfaces). Only
the surfaces' projected window is cast, so this over-counts a frame the subject does not fill."""
RENDER_BYTES_PER_CHUNK_RAY = 4 * KIB
"""Light-field activations per ray of a chunk without autograd (PE, sampled features, 256-wide layers)."""
RENDER_BYTES_PER_RAY = 64
"""Per shaded ray of the frame: uvs, indices, (N, 3) output kept until the canvas is filled."""
TRAIN_BYTES_PER_TEXEL = int(1.5 * KIB)
"""Saved activations of one paper-width U-Net forward + backward per atlas texel."""
TRAIN_BYTES_PER_CHUNK_RAY = 16 * KIB
"""Light-field activations saved for backward per ray of a chunk."""
TRAIN_BYTES_PER_RAY = 256
"""Per shaded ray of the step: ray batch, target and image gradient per ray."""
TRAIN_BYTES_PER_PIXEL = 64
"""Per image pixel of the step: target image, masks, shaded mask."""

PEAK_PROBE_ENV = {"MALLOC_MMAP_THRESHOLD_": "65536", "OMP_NUM_THREADS": "1"}
"""Environment of a fresh process that measures peaks (see the module docstring)."""

T = TypeVar("T")


def frame_features_bytes(features) -> int:
    """F of :func:`render_peak_bound`: the bytes of a frame's ``FrameFeatures`` (the inner and outer feature maps,
    texture channels included, and the inner normals that a reflected-view-direction variant keeps)."""
    maps = (features.inner, features.outer, features.normals, features.inner_texture, features.outer_texture)
    return sum(t.numel() * t.element_size() for t in maps if t is not None)


def render_peak_bound(features_bytes: int, pixels: int, chunk: int, rays: int) -> int:
    """Bytes ``render_frame`` may grow by (no autograd), one camera.

    Args:
        features_bytes: F, the frame's feature maps (2 maps x C x S^2 x 4 B for two surfaces, + 3 x S^2 x 4 B of
            normals for a reflected-view-direction variant): :func:`frame_features_bytes`.
        pixels: P, pixels of the image.
        chunk: c, rays per chunk of the light field.
        rays: N, shaded rays of the image.

    Returns:
        2 F + 320 B P + 4 KiB c + 64 B N + 16 MiB.
    """
    return (2 * features_bytes + RENDER_BYTES_PER_PIXEL * pixels + RENDER_BYTES_PER_CHUNK_RAY * chunk
            + RENDER_BYTES_PER_RAY * rays + SLACK)


def train_peak_bound(param_bytes: int, atlas_res: int, chunk: int, rays: int, pixels: int, unets: int = 2) -> int:
    """Bytes a ``train_step`` with ``ray_chunk = chunk`` may grow by once Adam's state exists.

    Returns:
        param bytes (gradients) + unets x 1.5 KiB S^2 + 16 KiB c + 256 B N + 64 B P + 16 MiB.
    """
    return (param_bytes + unets * TRAIN_BYTES_PER_TEXEL * atlas_res**2 + TRAIN_BYTES_PER_CHUNK_RAY * chunk
            + TRAIN_BYTES_PER_RAY * rays + TRAIN_BYTES_PER_PIXEL * pixels + SLACK)


def _status() -> dict[str, int]:
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmRSS:", "VmHWM:")):
                key, value = line.split(":")
                out[key] = int(value.split()[0]) * 1024
    return out


def peak_rss_growth(fn: Callable[[], T]) -> tuple[int, T]:
    """(growth of the peak resident set over the resident set before the call, in bytes; result).

    Raises:
        RuntimeError: not on Linux (no ``/proc/self/clear_refs`` to reset the peak).
    """
    if not Path("/proc/self/clear_refs").exists():
        raise RuntimeError("peak_rss_growth needs Linux /proc/self/clear_refs to reset the peak resident set")
    gc.collect()
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")  # reset VmHWM to the current resident set
    base = _status()["VmRSS"]
    result = fn()
    return _status()["VmHWM"] - base, result


RETAIN_MMAP_THRESHOLD = 32 * MIB
"""glibc's largest ``M_MMAP_THRESHOLD`` on 64-bit: blocks below it come from the heap."""
RETAIN_TRIM_THRESHOLD = 1 << 30
"""Freed memory at the top of the heap that glibc keeps instead of returning it (``M_TRIM_THRESHOLD``)."""


def retain_freed_memory() -> bool:
    """Make glibc malloc keep freed memory in the process instead of returning it to the system.

    A render or training loop allocates and frees the same maps every frame or step (U-Net
    activations, conv outputs of 1-64 MiB). By default glibc serves such blocks by ``mmap`` and
    unmaps them when freed, or trims them off the top of the heap, so every next allocation
    faults its pages in again, 4 kB at a time; in a VM that can cost a large part of a convolution's
    time for a fresh 16 MiB output. This sets
    ``M_MMAP_THRESHOLD`` to 32 MiB and ``M_TRIM_THRESHOLD`` to 1 GiB (the same as the environment
    variables ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``). The resident set then stays
    near its peak until the process exits; peaks themselves do not change.

    The CLI's train / eval / render / demo commands and ``make bench`` call it once at start.

    Returns:
        True when applied (Linux with glibc), False elsewhere (nothing changed).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc <malloc.h>
    return bool(mallopt(m_mmap_threshold, RETAIN_MMAP_THRESHOLD)) and bool(
        mallopt(m_trim_threshold, RETAIN_TRIM_THRESHOLD)
    )
