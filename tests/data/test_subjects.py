"""Capture formats: the ``Subject`` registry, the DynaCap parser, and convert consuming a ``Subject``."""

from __future__ import annotations

import dataclasses
import json

import pytest

from deliffas.data.convert import ConvertConfig, convert
from deliffas.data.shards import read_manifest
from deliffas.data.subjects import Subject, SubjectOptions, parse_dynacap, parse_subject, subject_format_names
from deliffas.io.format_registry import CaptureFormat, register_capture_format


def test_dynacap_is_detected(subject, tiny):
    s = parse_subject(subject)
    assert isinstance(s, Subject) and s.format == "dynacap"
    assert len(s.cameras) == tiny["num_cameras"] and list(s.sequences) == ["training", "testing"]
    train = s.sequences["training"]
    assert len(train.frames) == tiny["num_frames"] and train.poses.dofs.shape[0] == tiny["num_frames"]
    assert (train.width, train.height) == (tiny["width"], tiny["height"]) and train.images.layout == "images"
    assert s.template.kind == "ddc" and s.template.option("skinning") == "dqs"
    assert s.test_cameras == tuple(json.loads((subject / "split.json").read_text())["test_cameras"])


def test_options_reach_the_parser(subject):
    s = parse_subject(subject, "dynacap", SubjectOptions(skinning="lbs", sequences=("testing",), test_cameras=(0,),
                                                         layout="videos"))
    assert list(s.sequences) == ["testing"] and s.test_cameras == (0,)
    assert s.template.option("skinning") == "lbs" and s.sequences["testing"].images.layout == "videos"


def test_unknown_and_unrecognised_formats(tmp_path):
    with pytest.raises(ValueError, match=r"unknown capture format 'nosuchformat'; expected one of .*dynacap"):
        parse_subject(tmp_path, "nosuchformat")
    with pytest.raises(ValueError, match=r"not a capture of any known format \(.*dynacap.*\); pass --format"):
        parse_subject(tmp_path)
    with pytest.raises(FileNotFoundError, match="capture folder not found"):
        parse_subject(tmp_path / "missing")
    with pytest.raises(ValueError, match="'dynacap': detect_subject, parse_subject registered already"):
        register_capture_format(CaptureFormat("dynacap", detect_subject=lambda p: False, parse_subject=parse_dynacap))
    with pytest.raises(ValueError, match=r"capture format 'colmap' has no parse_subject; expected one of .*dynacap"):
        parse_subject(tmp_path, "colmap")  # a camera-only format


def test_a_format_is_one_registration_and_convert_takes_its_subject(tmp_path, subject, converted):
    """A toy format (DynaCap read by another name) registered here converts to the same shards."""
    def parse(root, options):
        return dataclasses.replace(parse_dynacap(root, options), format="test_renamed")

    register_capture_format(CaptureFormat("test_renamed", detect_subject=lambda p: False, parse_subject=parse))
    assert "test_renamed" in subject_format_names()
    s = parse_subject(subject, "test_renamed")
    out = tmp_path / "out"
    convert(s, out, ConvertConfig(shard_frames=2, atlas_res=32, progress=False))
    mine, ref = read_manifest(out), read_manifest(converted)
    assert mine["config"]["format"] == "test_renamed" and ref["config"]["format"] == "dynacap"
    assert [e["sha256"] for e in mine["shards"]] == [e["sha256"] for e in ref["shards"]]
