"""One synthetic capture (256^2) and its shards, made once per benchmark run and shared by the modules."""

from __future__ import annotations

import functools
import tempfile
import time
from pathlib import Path

FRAMES, TEST_FRAMES, CAMERAS, SIZE = 12, 2, 6, 256


@functools.lru_cache(maxsize=1)
def bench_capture() -> tuple[Path, Path, float]:
    """(subject folder, shards folder, conversion seconds) of a 12-frame, 6-camera capture at 256^2."""
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture

    tmp = Path(tempfile.mkdtemp(prefix="deliffas-bench-"))
    synthesize_capture(tmp / "subject", SynthConfig(num_frames=FRAMES, num_test_frames=TEST_FRAMES, num_cameras=CAMERAS,
                                                    width=SIZE, height=SIZE, test_cameras=(CAMERAS - 1,), seed=0))
    t0 = time.perf_counter()
    convert(tmp / "subject", tmp / "shards", ConvertConfig(atlas_res=256, progress=False, shard_frames=6))
    return tmp / "subject", tmp / "shards", time.perf_counter() - t0
