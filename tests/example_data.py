"""Small inputs for the tests: the scripts in ``examples/`` (test_examples.py, test_wheel.py) and the shared tiny
captures of the engine, benchmark and web tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def easymocap_rig(folder: Path) -> Path:
    """Two 48 x 48 cameras looking at the body, written as EasyMocap's intri/extri files into ``folder``."""
    from deliffas.io.camera_formats import write_cameras
    from deliffas.io.cameras import Camera, look_at

    cams = [Camera(f"c{i}", np.array([[40.0, 0, 24], [0, 40, 24], [0, 0, 1]]),
                   look_at(np.array([3000.0 * np.sin(i), 900, 3000 * np.cos(i)]), np.array([0.0, 900, 0])), 48, 48)
            for i in range(2)]
    write_cameras(cams, folder, "easymocap")
    return folder


def small_shards(folder: Path) -> Path:
    """A 2-frame, 3-camera synthetic capture at 32 x 32 in ``folder/s``, converted (atlas 16) into ``folder/shards``."""
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture

    synthesize_capture(folder / "s", SynthConfig(num_frames=2, num_test_frames=1, num_cameras=3, width=32, height=32))
    convert(folder / "s", folder / "shards", ConvertConfig(atlas_res=16, progress=False))
    return folder / "shards"


def tiny_capture(folder: Path, num_test_frames: int = 2) -> tuple[Path, Path]:
    """(subject, shards): 6 training frames at 48 x 48 from 4 cameras (camera 3 held out) in ``folder/subject``,
    converted with a 32 x 32 atlas into ``folder/shards``."""
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture

    synthesize_capture(folder / "subject", SynthConfig(num_frames=6, num_test_frames=num_test_frames, num_cameras=4,
                                                       width=48, height=48, test_cameras=(3,), seed=0))
    convert(folder / "subject", folder / "shards", ConvertConfig(atlas_res=32, progress=False))
    return folder / "subject", folder / "shards"
