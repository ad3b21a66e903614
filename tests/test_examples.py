"""The examples in ``examples/`` run on small data, as another project would start from them."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest
from example_data import easymocap_rig, small_shards

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
    _run("02_uv_maps.py", [str(tmp_path / "out"), "--cameras", str(easymocap_rig(tmp_path / "emc"))], monkeypatch)
    assert sorted(p.name for p in (tmp_path / "out").glob("uv_*.png")) == ["uv_c0.png", "uv_c1.png"]


def test_custom_training_example(tmp_path, monkeypatch, capsys):
    pytest.importorskip("h5py")
    _run("03_custom_training.py", [str(small_shards(tmp_path)), "--steps", "5"], monkeypatch)
    assert "step 5:" in capsys.readouterr().out
