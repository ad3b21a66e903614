"""The capture-format registry: parts merge into one record, a capability is given once, and an installed
package adds a format through the ``deliffas.formats`` entry point with no deliffas file changed."""

from __future__ import annotations

import textwrap

import pytest

import deliffas.plugins as plugins
from capture_cameras import assert_same_cameras, rig
from deliffas.io import format_registry
from deliffas.io.camera_formats import camera_format_names, detect_camera_format, read_cameras, write_cameras
from deliffas.io.format_registry import CaptureFormat, capture_format, capture_formats, register_capture_format


@pytest.fixture
def registry(monkeypatch):
    """A copy of the registry (and of the loaded plug-in groups) that the test may change."""
    capture_formats()  # the built-ins first
    monkeypatch.setattr(format_registry, "_FORMATS", dict(format_registry._FORMATS))
    monkeypatch.setattr(plugins, "_LOADED", set())
    return format_registry._FORMATS


def test_parts_merge_into_one_record_and_a_capability_is_given_once(registry):
    read = lambda path, size: []  # noqa: E731
    register_capture_format(CaptureFormat("toy", "Toy", detect_cameras=lambda p: False, read_cameras=read))
    merged = register_capture_format(CaptureFormat("toy", parse_subject=lambda root, options: None))
    assert merged is capture_format("toy") and merged.read_cameras is read and merged.parse_subject is not None
    assert merged.write_cameras is None and merged.export is None  # absent, not stubbed
    assert "toy" not in camera_format_names()  # it cannot write cameras
    both = capture_formats("read_cameras", "parse_subject")  # built-ins too once data.subjects is imported
    assert "toy" in [f.name for f in both] and all(f.read_cameras and f.parse_subject for f in both)
    with pytest.raises(ValueError, match="'toy': read_cameras registered already"):
        register_capture_format(CaptureFormat("toy", read_cameras=read))
    with pytest.raises(ValueError, match=r"camera format 'toy' has no write_cameras; expected one of dynacap"):
        write_cameras(rig(), "x", "toy")
    with pytest.raises(ValueError, match="unknown capture format 'nope'; expected one of"):
        capture_format("nope")


def test_builtins_come_first_in_their_order():
    names = [f.name for f in capture_formats()]
    assert names[:2] == ["dynacap", "colmap"] and names.index("zju") < names.index("easymocap")


PLUGIN = '''
"""A JSON list of cameras (K, world_to_cam, size): a capture format from another package."""
import json
from pathlib import Path

import numpy as np

from deliffas.io.cameras import Camera
from deliffas.io.format_registry import CaptureFormat, register_capture_format


def _read(path, size):
    return [Camera(c["name"], np.array(c["K"]), np.array(c["E"]), *c["size"]) for c in json.loads(Path(path).read_text())]


def _write(cameras, out, options):
    rows = [{"name": c.name, "K": c.K.tolist(), "E": c.world_to_cam.tolist(), "size": [c.width, c.height]}
            for c in cameras]
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(rows))
    return Path(out)


register_capture_format(CaptureFormat(
    "toyjson", "toy cameras.toy.json", camera_path="cameras.toy.json", distortion=(), stores_size=True,
    detect_cameras=lambda p: p.name.endswith(".toy.json"), read_cameras=_read, write_cameras=_write))
'''


def test_an_installed_package_adds_a_format(registry, tmp_path, monkeypatch):
    """A fake distribution on sys.path declares ``deliffas.formats``; deliffas finds and uses it."""
    (tmp_path / "toy_formats.py").write_text(textwrap.dedent(PLUGIN))
    dist = tmp_path / "toy_formats-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-formats\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[deliffas.formats]\ntoyjson = toy_formats\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(__import__("sys").modules, "toy_formats", raising=False)
    assert "toyjson" in camera_format_names()
    (tmp_path / "cap").mkdir()
    out = write_cameras(rig(), tmp_path / "cap", "toyjson")  # a folder gets the format's camera_path
    assert out == tmp_path / "cap" / "cameras.toy.json" and detect_camera_format(out) == "toyjson"
    assert_same_cameras(rig(), read_cameras(out))


def test_a_broken_plug_in_is_named(registry, tmp_path, monkeypatch):
    (tmp_path / "broken_format.py").write_text("raise RuntimeError('missing dependency')\n")
    dist = tmp_path / "broken_format-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-format\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[deliffas.formats]\nbroken = broken_format\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(plugins.PluginError, match=r"plug-in broken = broken_format \(entry point deliffas.formats, "
                                                  r"from broken-format\) does not import: RuntimeError: missing"):
        capture_formats()
