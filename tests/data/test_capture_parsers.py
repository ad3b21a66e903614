"""Capture-format parsers: synth (SMPL body) -> export as X -> parse X -> convert == a direct conversion.

Each parser reads files written by ``deliffas.data.export_capture`` through the ``deliffas.io`` writers
(another code path than the parser's). Shards are compared with a conversion of the synthetic subject
itself: cameras to 1e-6 relative, images exact where the format stores PNG and within JPEG loss where
it stores JPEG (written at quality 100), masks exact (PNG) or within JPEG loss, and the posed template
(SMPL parameters in each dataset's own form) to 1e-3 mm.
"""

from __future__ import annotations

import logging
import shutil

import cv2
import numpy as np
import pytest

from deliffas.data.convert import ConvertConfig, convert
from deliffas.data.export_capture import export_format_names
from deliffas.data.shards import ShardSet
from deliffas.data.subjects import SubjectOptions, parse_subject
from deliffas.io.formats.easymocap import read_easymocap_cameras, write_easymocap_cameras

JPEG_MASKS = {"thuman4", "dna"}
"""Formats whose masks are JPEG (the others store PNG)."""


@pytest.fixture(scope="session")
def direct(tmp_path_factory, smpl_subject):
    """The synthetic SMPL subject's training sequence converted directly."""
    out = tmp_path_factory.mktemp("direct") / "out"
    convert(smpl_subject, out, ConvertConfig(sequences=("training",), atlas_res=16, shard_frames=4, progress=False))
    return ShardSet(out)


@pytest.mark.parametrize("fmt", export_format_names())
def test_round_trip(fmt, exported, smpl_model, direct, tmp_path):
    root = exported(fmt)
    subject = parse_subject(root, options=SubjectOptions(template=str(smpl_model)))
    assert subject.format == fmt and list(subject.sequences) == ["training"]
    out = tmp_path / "out"
    convert(subject, out, ConvertConfig(atlas_res=16, shard_frames=4, progress=False))
    got, ref = ShardSet(out), direct
    gm, rm = got.meta, ref.meta
    assert gm.camera_names == rm.camera_names and np.array_equal(gm.sizes, rm.sizes)
    np.testing.assert_allclose(gm.K, rm.K, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(gm.world_to_cam, rm.world_to_cam, rtol=1e-6, atol=1e-6 * 4000)
    assert got.frames("training") == ref.frames("training") == [0, 1, 2, 3]
    for f in range(4):
        gs, gr = got.locate("training", f)
        rs, rr = ref.locate("training", f)
        np.testing.assert_allclose(gs.geometry("inner_verts", [f]), rs.geometry("inner_verts", [f]), atol=1e-3)
        for col in range(4):
            rgb, mask = gs.image(gr, col)
            ref_rgb, ref_mask = rs.image(rr, col)
            err = np.abs(rgb.astype(int) - ref_rgb)
            assert err.mean() < 2.0 and np.percentile(err, 99) <= 40, (fmt, f, col, err.mean())  # JPEG q100, 4:2:0
            merr = np.abs(mask.astype(int) - ref_mask)
            assert merr.max() <= (8 if fmt in JPEG_MASKS else 0), (fmt, f, col, merr.max())


def test_rhth_posing_matches_direct_rotation(exported, smpl_model, smpl_subject):
    """ZJU Rh/Th: the SMPL rows pose exactly what R(Rh) X + Th poses (X: the body with zero root and translation)."""
    import torch

    from deliffas.geometry.templates import build_template
    from deliffas.io.camera_conventions import rotvec_to_matrix
    from deliffas.io.formats.zju_mocap import read_zju_params, zju_params_path

    root = exported("zju")
    subject = parse_subject(root, options=SubjectOptions(template=str(smpl_model)))
    template = build_template(subject.template, dtype=torch.float64)
    for f in range(4):
        rec = read_zju_params(zju_params_path(root, f))
        bare = np.concatenate([np.zeros(3), rec.poses[0], rec.shapes[0]])[None]
        X = template.pose(torch.as_tensor(bare)).numpy()[0]
        expect = X @ rotvec_to_matrix(rec.Rh[0]).T + rec.Th[0] * 1000.0
        got = template.pose(torch.as_tensor(subject.sequences["training"].poses.dofs[f:f + 1])).numpy()[0]
        assert np.abs(got - expect).max() < 1e-3
    ref = parse_subject(smpl_subject)
    np.testing.assert_allclose(subject.sequences["training"].poses.dofs, ref.sequences["training"].poses.dofs[:4],
                               atol=1e-9)


def test_distortion_is_undone_at_read_time(exported, smpl_model, tmp_path, caplog):
    root = tmp_path / "cap"
    shutil.copytree(exported("easymocap"), root)
    cams = read_easymocap_cameras(root / "intri.yml")
    D = np.array([-0.12, 0.03, 0.001, -0.002, 0.0])
    cams[1] = type(cams[1])(cams[1].name, cams[1].K, D, cams[1].R, cams[1].T, cams[1].width, cams[1].height)
    write_easymocap_cameras(root, cams)
    with caplog.at_level(logging.WARNING):
        subject = parse_subject(root, options=SubjectOptions(template=str(smpl_model)))
    assert sum("lens distortion" in r.getMessage() for r in caplog.records) == 1
    assert all("distortion" not in c.extra for c in subject.cameras)
    raw = cv2.cvtColor(cv2.imread(str(root / "images" / "1" / "000002.jpg")), cv2.COLOR_BGR2RGB)
    rgb, _ = subject.sequences["training"].images.open().read(2, 1)
    expect = cv2.undistort(raw, cams[1].K, D)
    assert np.abs(rgb.astype(int) - expect).mean() < 0.5 and not np.array_equal(rgb, raw)
    assert np.array_equal(subject.sequences["training"].images.open().read(2, 0)[0],
                          cv2.cvtColor(cv2.imread(str(root / "images" / "0" / "000002.jpg")), cv2.COLOR_BGR2RGB))


@pytest.mark.parametrize("fmt", ["zju", "easymocap", "thuman4", "dna", "actorshq"])
def test_smpl_model_is_required(fmt, exported):
    with pytest.raises(ValueError, match="--template"):
        parse_subject(exported(fmt))


def test_actorshq_without_smpl_needs_meshes(exported, smpl_model, tmp_path):
    root = tmp_path / "cap"
    shutil.copytree(exported("actorshq"), root)
    (root / "poses.npz").unlink()
    with pytest.raises(ValueError, match="--meshes"):
        parse_subject(root, options=SubjectOptions(template=str(smpl_model)))
    subject = parse_subject(root, options=SubjectOptions(template=str(smpl_model),
                                                         motions=(str(exported("actorshq") / "poses.npz"),)))
    assert subject.sequences["training"].poses.num_frames == 4


def test_dna_conversion_opens_each_smc_once(exported, smpl_model, monkeypatch, tmp_path):
    """A conversion keeps one ``SmcFrameSource`` open across its shards (``SmcFramesSpec.keep_open``): each ``.smc``
    is scanned once, not once per shard, and closed at the end; the shards equal those of one source per shard."""
    import deliffas.io.formats.dna_rendering as dna

    subject = parse_subject(exported("dna"), options=SubjectOptions(template=str(smpl_model)))
    scanned, opened = [], []
    scan = dna.looping_global_heap
    monkeypatch.setattr(dna, "looping_global_heap", lambda path: scanned.append(path.name) or scan(path))
    real_close = dna.SmcFile.close
    monkeypatch.setattr(dna.SmcFile, "close", lambda self: opened.remove(self) or real_close(self))
    real_init = dna.SmcFile.__init__
    monkeypatch.setattr(dna.SmcFile, "__init__", lambda self, path: real_init(self, path) or opened.append(self))
    convert(subject, tmp_path / "kept", ConvertConfig(atlas_res=16, shard_frames=1, progress=False))
    assert len(ShardSet(tmp_path / "kept").manifest["shards"]) == 4
    assert scanned == ["cap_dna.smc"] * 2  # the pre-conversion check's source, then the shards' one (5 before)
    assert opened == []  # every file closed
    monkeypatch.setattr(type(subject.sequences["training"].images), "keep_open", False)  # one source per shard
    convert(subject, tmp_path / "per_shard", ConvertConfig(atlas_res=16, shard_frames=1, progress=False))
    assert len(scanned) == 2 + 5 and opened == []
    kept, per_shard = ShardSet(tmp_path / "kept").manifest, ShardSet(tmp_path / "per_shard").manifest
    assert [s["sha256"] for s in kept["shards"]] == [s["sha256"] for s in per_shard["shards"]]


def test_dna_parser_opens_each_smc_once(exported, smpl_model, monkeypatch):
    """Every ``SmcFile`` open scans the whole file's HDF5 heaps (``io.infra.hdf5_heaps``, about 0.7 s per GB): the parser
    opens the main file and its ``_annots.smc`` once each (it opened them up to 8 times)."""
    import deliffas.io.formats.dna_rendering as dna

    root = exported("dna")
    scanned = []
    scan = dna.looping_global_heap
    monkeypatch.setattr(dna, "looping_global_heap", lambda path: scanned.append(path.name) or scan(path))
    parse_subject(root, options=SubjectOptions(template=str(smpl_model)))
    assert sorted(scanned) == sorted(p.name for p in root.glob("*.smc")), scanned
