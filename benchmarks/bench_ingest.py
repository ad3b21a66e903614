"""The mask/keypoint stage of ``deliffas ingest``: images per second of MediaPipe Pose (full model, segmentation,
video mode) on frames of the real Pose2Sim recording at the default size (540x960), decode and resize included
(smoke mode: 4 frames at 136x240)."""

from __future__ import annotations

import time
from pathlib import Path

from benchmarks.common import Result, sized

RECORDING = Path(__file__).resolve().parents[2] / "shared" / "real-captures" / "pose2sim-demo"


def run() -> list[Result]:
    from deliffas.io.recording import StreamReader, find_streams
    from deliffas.data.ingest.detect import PersonDetector, require_detector
    from deliffas.data.ingest.frames import output_size

    if not (RECORDING / "videos").is_dir():
        return [Result("ingest", "skipped: ../shared/real-captures/pose2sim-demo absent", 0.0, "")]
    try:
        require_detector()
    except ValueError:
        return [Result("ingest", "skipped: MediaPipe 0.10.21 not installed (make ingest-setup)", 0.0, "")]
    import cv2

    stream = find_streams(RECORDING)[0]
    size = output_size(stream.width / stream.height, sized(960, 240))
    n = sized(60, 4)
    with StreamReader(stream) as reader, PersonDetector(video=True) as detector:
        frames = [cv2.resize(rgb, size, interpolation=cv2.INTER_AREA) for _, rgb in reader.frames(range(n))]
        detector(frames[0])  # warm-up: the model's first call
        t0 = time.perf_counter()
        for rgb in frames[1:]:
            detector(rgb)
        seconds = time.perf_counter() - t0
    rate = (len(frames) - 1) / seconds
    return [Result("ingest", f"person mask + 2-D keypoints, {size[0]}x{size[1]}, {len(frames) - 1} frames of {stream.path.name}",
                   rate, "images/s")]
