"""One synthetic capture and its shards, made once per benchmark run and shared by the modules: 12 + 2 frames,
6 cameras, 256^2, atlas side 256 (smoke mode: 3 + 1 frames, 5 cameras, 64^2, atlas side 32)."""

from __future__ import annotations

import functools
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

from benchmarks.common import sized


class CaptureSize(NamedTuple):
    """Frames, novel-pose frames, cameras, image side and atlas side of the bench capture."""

    frames: int
    test_frames: int
    cameras: int
    size: int
    atlas: int


FULL = CaptureSize(12, 2, 6, 256, 256)
SMOKE = CaptureSize(3, 1, 5, 64, 32)


def capture_size() -> CaptureSize:
    """The bench capture's size in this mode (:data:`FULL`, or :data:`SMOKE` in smoke mode)."""
    return sized(FULL, SMOKE)


def bench_capture() -> tuple[Path, Path, float]:
    """(subject folder, shards folder, conversion seconds) of the bench capture (:func:`capture_size`)."""
    return _make(capture_size())


@functools.lru_cache(maxsize=None)
def _make(dims: CaptureSize) -> tuple[Path, Path, float]:
    """The capture of size ``dims`` in a new temporary folder, synthesized and converted."""
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture

    tmp = Path(tempfile.mkdtemp(prefix="deliffas-bench-"))
    synthesize_capture(tmp / "subject", SynthConfig(num_frames=dims.frames, num_test_frames=dims.test_frames,
                                                    num_cameras=dims.cameras, width=dims.size, height=dims.size,
                                                    test_cameras=(dims.cameras - 1,), seed=0))
    t0 = time.perf_counter()
    convert(tmp / "subject", tmp / "shards", ConvertConfig(atlas_res=dims.atlas, progress=False,
                                                           shard_frames=max(1, dims.frames // 2)))
    return tmp / "subject", tmp / "shards", time.perf_counter() - t0
