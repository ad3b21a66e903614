"""The examples in ``examples/`` run on small data, as another project would start from them."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(name: str, argv: list[str], monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", [name] + argv)
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")


def test_geometry_example(tmp_path, monkeypatch):
    _run("01_geometry.py", [str(tmp_path), "--frames", "3", "--atlas", "32"], monkeypatch)
    assert len(list(tmp_path.glob("posed_*.obj"))) == 3 and len(list(tmp_path.glob("shell_*.obj"))) == 3
    import numpy as np

    with np.load(tmp_path / "normal_maps.npz") as z:
        assert z["inner"].shape == (3, 9, 32, 32) and z["outer"].dtype == np.float16


def test_uv_maps_example(tmp_path, monkeypatch):
    from deliffas.io.camera_formats import write_cameras
    from deliffas.io.cameras import Camera, look_at
    import numpy as np

    cams = [Camera(f"c{i}", np.array([[40.0, 0, 24], [0, 40, 24], [0, 0, 1]]),
                   look_at(np.array([3000.0 * np.sin(i), 900, 3000 * np.cos(i)]), np.array([0.0, 900, 0])), 48, 48)
            for i in range(2)]
    write_cameras(cams, tmp_path / "emc", "easymocap")
    _run("02_uv_maps.py", [str(tmp_path / "out"), "--cameras", str(tmp_path / "emc")], monkeypatch)
    assert sorted(p.name for p in (tmp_path / "out").glob("uv_*.png")) == ["uv_c0.png", "uv_c1.png"]


def test_custom_training_example(tmp_path, monkeypatch, capsys):
    pytest.importorskip("h5py")
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture

    synthesize_capture(tmp_path / "s", SynthConfig(num_frames=2, num_test_frames=1, num_cameras=3, width=32, height=32))
    convert(tmp_path / "s", tmp_path / "shards", ConvertConfig(atlas_res=16, progress=False))
    _run("03_custom_training.py", [str(tmp_path / "shards"), "--steps", "5"], monkeypatch)
    assert "step 5:" in capsys.readouterr().out
