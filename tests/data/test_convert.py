"""synth -> convert -> verify: bit-exact images, schema, checksums, resume, parallel determinism."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from deliffas.cli import main as cli_main
from deliffas.data.convert import ConvertConfig, convert, parse_frame_range
from deliffas.io.formats.dynacap.character import read_character
from deliffas.io.formats.dynacap.frames import ImageFolderSource
from deliffas.data.shards import MANIFEST_NAME, ShardSet, read_manifest, verify_shards, write_manifest

CFG = dict(shard_frames=2, atlas_res=32, progress=False)


def _manifest_bytes(out: Path) -> bytes:
    return (out / MANIFEST_NAME).read_bytes()


def _tree_state(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


def test_round_trip_images_bit_exact(subject, converted):
    checked = verify_shards(converted)
    assert checked.problems == () and checked.ok and checked.deep
    sset = ShardSet(converted)
    assert checked.to_json() == {"out": str(converted), "deep": True, "shards": len(sset.shards), "ok": True,
                                 "problems": []}
    assert sset.complete and [s.name for s in sset.shards] == [
        "shards/training-00000.h5", "shards/training-00001.h5", "shards/testing-00000.h5"]
    for seq, n in (("training", 3), ("testing", 1)):
        src = ImageFolderSource(subject / seq)
        assert sset.frames(seq) == list(range(n))
        for f in range(n):
            shard, row = sset.locate(seq, f)
            for col, cam in enumerate(shard.camera_ids):
                rgb, mask = shard.image(row, col)
                ref_rgb, ref_mask = src.read(f, int(cam))
                assert np.array_equal(rgb, ref_rgb) and np.array_equal(mask, ref_mask)


def test_schema(converted):
    meta = ShardSet(converted).meta
    assert meta.camera_names == ["0", "1", "2", "3"] and meta.sizes.tolist() == [[64, 64]] * 4
    assert meta.train_cameras.tolist() == [0, 1, 3] and meta.test_cameras.tolist() == [2]
    assert meta.texel_face.shape == (32, 32) and meta.attrs["window"] == 2 and meta.attrs["codec"] == "raw"
    assert np.allclose(meta.outer_offsets, 30.0) and len(meta.attrs["character_sha256"]) == 64
    with h5py.File(converted / "shards" / "training-00001.h5") as f:
        assert f["frames"][()].tolist() == [2]
        g = f["geometry"]
        assert g["frames"][()].tolist() == [0, 1, 2]  # frame 2 and its window 1, 0
        assert f["window_rows"][()].tolist() == [[2, 1, 0]]
        V = meta.rest_verts.shape[0]
        assert g["inner_verts"].shape == (3, V, 3) and g["inner_verts"].dtype == np.float32
        assert g["normal_maps_outer"].shape == (3, 3, 32, 32) and g["normal_maps_outer"].dtype == np.float16
        assert f["rgba"].shape == (1, 4, 64, 64, 4) and f["rgba"].chunks == (1, 1, 64, 64, 4)
        nm = g["normal_maps_inner"][()].astype(np.float32)
        norms = np.linalg.norm(nm, axis=1)
        assert np.allclose(norms[meta.texel_valid[None].repeat(3, 0)], 1.0, atol=2e-3)
        assert np.all(norms[~meta.texel_valid[None].repeat(3, 0)] == 0)
        offset = np.linalg.norm(g["outer_verts"][()] - g["inner_verts"][()], axis=-1)
        assert np.allclose(offset, 30.0, atol=1e-3)


def test_verify_catches_flipped_byte_and_missing_shard(converted_copy, capsys):
    out = converted_copy
    assert cli_main(["verify", str(out)]) == 0
    victim = out / "shards" / "training-00001.h5"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    assert cli_main(["verify", str(out)]) == 1
    err = capsys.readouterr().err
    assert "shards/training-00001.h5: checksum mismatch" in err and "training-00000" not in err
    (out / "shards" / "testing-00000.h5").unlink()
    assert cli_main(["verify", str(out)]) == 1
    err = capsys.readouterr().err
    assert "shards/testing-00000.h5: missing shard file" in err
    assert cli_main(["verify", str(out), "--quick", "--json"]) == 1
    printed = json.loads(capsys.readouterr().out)
    assert printed["ok"] is False and printed["deep"] is False and any("missing shard file" in p
                                                                        for p in printed["problems"])


def test_verify_reports_unreadable_and_incomplete(converted_copy):
    out = converted_copy
    victim = out / "shards" / "training-00000.h5"
    victim.write_bytes(victim.read_bytes()[:1000])  # truncated: unreadable
    m = read_manifest(out)
    m["shards"] = [s for s in m["shards"] if s["name"] != "shards/testing-00000.h5"]
    m["complete"] = False
    write_manifest(out, m)
    problems = verify_shards(out).problems
    assert any("training-00000.h5: unreadable" in p for p in problems)
    assert any("testing-00000.h5: planned but not converted" in p for p in problems)


def test_resume_after_interruption_gives_identical_manifest(subject, converted, tmp_path):
    """Simulated crash: one shard gone, a half-written temp file left, a partial manifest."""
    out = tmp_path / "out"
    convert(subject, out, ConvertConfig(**CFG))
    assert _manifest_bytes(out) == _manifest_bytes(converted)  # deterministic across runs
    m = read_manifest(out)
    m["shards"] = m["shards"][:1]
    m["complete"] = False
    write_manifest(out, m)
    (out / "shards" / "training-00001.h5").unlink()
    (out / "shards" / ".training-00001.h5.tmp-999").write_bytes(b"half a shard")
    with pytest.raises(FileExistsError, match="--resume"):
        convert(subject, out, ConvertConfig(**CFG))
    with pytest.raises(ValueError, match="atlas_res"):
        convert(subject, out, ConvertConfig(**{**CFG, "atlas_res": 16}, resume=True))
    res = convert(subject, out, ConvertConfig(**CFG, resume=True))
    assert (res.shards_skipped, res.shards_converted) == (2, 1)  # testing-00000 was renamed, never listed
    assert _manifest_bytes(out) == _manifest_bytes(converted)
    assert not list((out / "shards").glob(".*tmp*")) and verify_shards(out).problems == ()


def test_resume_recognises_its_own_start_before_the_first_manifest(subject, converted, tmp_path):
    """SIGKILL after OUT/shards (and meta.h5, a temporary manifest) exist but before the first manifest: --resume
    finishes the conversion; a plain run says to use --resume; a folder with anything else is still refused."""
    out = tmp_path / "out"
    (out / "shards").mkdir(parents=True)
    with pytest.raises(FileExistsError, match="start of an interrupted conversion .* use --resume"):
        convert(subject, out, ConvertConfig(**CFG))
    (out / "meta.h5").write_bytes(b"half of meta")
    (out / ".manifest.json.tmp-999").write_bytes(b"{")
    (out / "shards" / ".training-00000.h5.tmp-999").write_bytes(b"half a shard")
    res = convert(subject, out, ConvertConfig(**CFG, resume=True))
    assert res.shards_skipped == 0
    assert _manifest_bytes(out) == _manifest_bytes(converted) and verify_shards(out).problems == ()
    other = tmp_path / "other"
    (other / "shards").mkdir(parents=True)
    (other / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="holds no conversion; pass --overwrite"):
        convert(subject, other, ConvertConfig(**CFG, resume=True))
    (other / "notes.txt").unlink()
    (other / "shards" / "mine.h5").write_bytes(b"mine")
    with pytest.raises(FileExistsError, match="holds no conversion"):
        convert(subject, other, ConvertConfig(**CFG, resume=True))


@pytest.mark.slow  # a SIGKILL chain of real processes (17 s): `make test-slow`, as the others
def test_resume_after_sigkill(subject, converted, tmp_path):
    """A real `deliffas convert --jobs 1` killed with SIGKILL once its first shard is listed."""
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "deliffas", "convert", str(subject), str(out), "--shard-frames", "1",
           "--atlas-res", "32", "--no-progress"]
    proc = subprocess.Popen(cmd + ["--jobs", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    killed = False
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if len(read_manifest(out)["shards"]) >= 1:
                proc.send_signal(signal.SIGKILL)
                killed = True
                break
        except (FileNotFoundError, ValueError, KeyError):
            pass
        time.sleep(0.005)
    proc.wait(timeout=60)
    assert killed, f"conversion ended before its first shard was seen (rc {proc.returncode})"
    assert proc.returncode == -signal.SIGKILL
    partial = read_manifest(out)
    assert not partial["complete"] and 1 <= len(partial["shards"]) < len(partial["planned"])
    ref = tmp_path / "ref"
    convert(subject, ref, ConvertConfig(shard_frames=1, atlas_res=32, progress=False))
    res = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert _manifest_bytes(out) == _manifest_bytes(ref)
    assert cli_main(["verify", str(out)]) == 0


def test_parallel_conversion_is_identical(subject, converted, tmp_path):
    out = tmp_path / "out"
    convert(subject, out, ConvertConfig(**{**CFG, "jobs": 2}))
    assert _manifest_bytes(out) == _manifest_bytes(converted)


def test_lingering_dataset_handles_do_not_change_shard_bytes(subject, converted, tmp_path, monkeypatch):
    """A handle kept alive after its write (Dask's profiler thread holds the writer's frames for a moment)
    must not move chunks: before the writer turned the chunk cache off, a held handle kept chunks cached
    and they got file space in another order (--dask shards then differed from --jobs 1)."""
    held = []
    setitem, create = h5py.Dataset.__setitem__, h5py.Group.create_dataset

    def held_setitem(self, *args, **kwargs):
        held.append(self)
        return setitem(self, *args, **kwargs)

    def held_create(self, *args, **kwargs):
        ds = create(self, *args, **kwargs)
        held.append(ds)
        return ds

    monkeypatch.setattr(h5py.Dataset, "__setitem__", held_setitem)
    monkeypatch.setattr(h5py.Group, "create_dataset", held_create)
    out = tmp_path / "out"
    convert(subject, out, ConvertConfig(**CFG))
    assert held, "the probe saw no dataset writes"
    held.clear()
    assert _manifest_bytes(out) == _manifest_bytes(converted)


def test_video_layout_converts_to_the_same_shards(subject, converted, tmp_path):
    out = tmp_path / "out"
    before = _tree_state(subject)
    convert(subject, out, ConvertConfig(**CFG, layout="videos"))
    assert _tree_state(subject) == before  # the source folder is never written to
    a, b = read_manifest(out), read_manifest(converted)
    assert [s["sha256"] for s in a["shards"]] == [s["sha256"] for s in b["shards"]]


def test_partial_manifest_visibility(converted_copy):
    m = read_manifest(converted_copy)
    full = ShardSet(converted_copy)
    m["shards"], m["complete"] = m["shards"][:1], False
    write_manifest(converted_copy, m)
    sset = ShardSet(converted_copy)
    assert not sset.complete and sset.frames("training") == [0, 1] and sset.frames("testing") == []
    with pytest.raises(KeyError):
        sset.locate("training", 2)
    assert full.frames("training") == [0, 1, 2]


def test_frame_and_camera_selection_codecs_and_meshes(subject, tmp_path):
    out = tmp_path / "png"
    convert(subject, out, ConvertConfig(**CFG, frames="1:3", cameras=(1, 2), codec="png", sequences=("training",),
                                        meshes=(f"training={subject / 'training' / 'gt.meshes'}",)))
    sset = ShardSet(out)
    assert sset.frames("training") == [1, 2] and sset.meta.converted_cameras.tolist() == [1, 2]
    assert sset.meta.train_cameras.tolist() == [1] and sset.meta.test_cameras.tolist() == [2]
    assert sset.meta.attrs["surface"] == "meshes"
    shard, row = sset.locate("training", 2)
    rgb, mask = shard.image(row, 1)
    ref = ImageFolderSource(subject / "training").read(2, 2)
    assert np.array_equal(rgb, ref[0]) and np.array_equal(mask, ref[1])
    from deliffas.io.formats.dynacap.meshes import read_meshes

    gt = read_meshes(subject / "training" / "gt.meshes").verts
    assert np.allclose(shard.geometry("inner_verts", [shard.h5["window_rows"][row][0]])[0], gt[2], atol=1e-3)
    jpg = tmp_path / "jpg"
    convert(subject, jpg, ConvertConfig(**CFG, frames="2", cameras=(0,), codec="jpeg:90", sequences=("training",)))
    shard, row = ShardSet(jpg).locate("training", 2)
    rgb, mask = shard.image(row, 0)
    ref = ImageFolderSource(subject / "training").read(2, 0)
    assert np.array_equal(mask, ref[1]) and np.abs(rgb.astype(int) - ref[0]).mean() < 3


def test_template_variant_with_outer_obj(subject, tmp_path):
    """--template DIR: its character poses the surface, outer.obj gives per-vertex offsets."""
    from deliffas.io.formats.dynacap.character import ObjData, write_obj
    from deliffas.geometry.mesh_ops import vertex_normals

    char_path = next((subject / "character").glob("*.character"))
    variant = tmp_path / "variant"
    variant.mkdir()
    for p in char_path.parent.iterdir():
        (variant / p.name).write_bytes(p.read_bytes())
    c = read_character(char_path)
    d = np.linspace(10.0, 20.0, c.mesh.num_verts)
    outer = c.mesh.verts + d[:, None] * vertex_normals(c.mesh.verts, c.mesh.faces)
    write_obj(variant / "outer.obj", ObjData(outer, c.mesh.faces))
    out = tmp_path / "out"
    convert(subject, out, ConvertConfig(**CFG, template=str(variant), sequences=("testing",)))
    meta = ShardSet(out).meta
    assert meta.attrs["surface"] == "variant" and np.allclose(meta.outer_offsets, d, atol=1e-3)


def test_bad_inputs(subject, tmp_path):
    with pytest.raises(ValueError, match="inside the source"):
        convert(subject, subject / "out", ConvertConfig(**CFG))
    with pytest.raises(ValueError, match="cameras"):
        convert(subject, tmp_path / "o", ConvertConfig(**CFG, cameras=(7,)))
    with pytest.raises(ValueError, match="codec"):
        convert(subject, tmp_path / "o", ConvertConfig(**{**CFG, "codec": "webp"}))
    assert parse_frame_range("10:20:5") == slice(10, 20, 5) and parse_frame_range("::10") == slice(None, None, 10)
    with pytest.raises(ValueError, match="STEP"):
        parse_frame_range("0:10:0")


def test_process_map_does_not_hang_on_a_dead_worker():
    from concurrent.futures.process import BrokenProcessPool

    from deliffas.parallel import process_map

    assert sorted(process_map(abs, [(-2,), (3,), (-1,)], 2, poll_s=0.2)) == [1, 2, 3]
    t0 = time.monotonic()
    with pytest.raises((RuntimeError, BrokenProcessPool)):
        list(process_map(os._exit, [(3,), (4,), (5,)], 2, poll_s=0.2))
    assert time.monotonic() - t0 < 30


def test_mask_folder_replaces_alpha(subject, tmp_path):
    import shutil

    import cv2

    subj = tmp_path / "subject"
    shutil.copytree(subject, subj)
    pattern = (np.indices((64, 64)).sum(axis=0) % 3 == 0).astype(np.uint8) * 255
    for cam in range(4):
        d = subj / "training" / "foregroundSegmentation" / str(cam)
        d.mkdir(parents=True)
        for f in range(3):
            cv2.imwrite(str(d / f"image_c_{cam}_f_{f}.png"), np.roll(pattern, cam + f, axis=1))
    for layout in ("images", "videos"):
        out = tmp_path / layout
        # the striped masks are a test pattern, not a silhouette: the silhouette check would (rightly) refuse them
        convert(subj, out, ConvertConfig(**CFG, sequences=("training",), masks="foregroundSegmentation", layout=layout,
                                         check=False))
        shard, row = ShardSet(out).locate("training", 2)
        rgb, mask = shard.image(row, 3)
        assert np.array_equal(mask, np.roll(pattern, 5, axis=1))
        assert np.array_equal(rgb, ImageFolderSource(subject / "training").read(2, 3)[0])


def _edit_shard(out, name, edit):
    """Apply ``edit(h5py.File)`` to a shard and record its new checksum, so only the schema is wrong."""
    import h5py

    from deliffas.io.infra.files import sha256_file

    p = out / name
    with h5py.File(p, "r+") as f:
        edit(f)
    m = read_manifest(out)
    for s in m["shards"]:
        if s["name"] == name:
            s["sha256"], s["bytes"] = sha256_file(p), p.stat().st_size
    write_manifest(out, m)


def _replace(f, key, data):
    del f[key]
    f.create_dataset(key, data=data)


@pytest.mark.parametrize("edit, match", [
    (lambda f: f["geometry"].__delitem__("outer_verts"), "dataset 'outer_verts' missing"),
    (lambda f: _replace(f, "geometry/inner_verts", f["geometry/inner_verts"][()][:, :5]), "'geometry/inner_verts' has shape"),
    (lambda f: _replace(f, "rgba", f["rgba"][()].astype(np.float32)), "'rgba' has dtype float32, expected uint8"),
    (lambda f: _replace(f, "window_rows", f["window_rows"][()] + 50), "'window_rows' points outside"),
    (lambda f: _replace(f, "frames", f["frames"][()] + 1), "differ from the manifest"),
])
def test_verify_checks_the_shard_schema(converted_copy, edit, match):
    _edit_shard(converted_copy, "shards/training-00000.h5", edit)
    problems = verify_shards(converted_copy).problems
    assert any(p.startswith("shards/training-00000.h5: ") and match in p for p in problems), problems
    assert not any("checksum" in p for p in problems)


def test_verify_refuses_names_outside_and_broken_manifests(converted_copy, capsys):
    out = converted_copy
    m = read_manifest(out)
    m["shards"][0]["name"] = "../../etc/passwd"
    write_manifest(out, m)
    assert any("outside the output folder; refused" in p for p in verify_shards(out).problems)
    with pytest.raises(ValueError, match="outside the output folder"):
        ShardSet(out)
    m["shards"] = {"not": "a list"}
    (out / "manifest.json").write_text(json.dumps(m))
    assert cli_main(["verify", str(out)]) == 1
    assert "'shards' must be a list" in capsys.readouterr().err


def test_dataset_names_a_corrupt_shard(converted_copy):
    from deliffas.data.dataset import ShardDataset
    from deliffas.data.shards import ShardReadError

    _edit_shard(converted_copy, "shards/training-00000.h5", lambda f: f["geometry"].__delitem__("normal_maps_inner"))
    ds = ShardDataset(converted_copy, split="train", temporal_window=2, protocol="all")
    with pytest.raises(ShardReadError, match=r"training-00000\.h5: cannot read frame"):
        ds[0]


@pytest.mark.parametrize("edit, match", [
    # frame 1's window row points at frame 0's geometry: frame 1 would be served with frame 0's surface
    (lambda f: _replace(f, "window_rows", np.zeros_like(f["window_rows"][()])), "points at geometry of other frames"),
    (lambda f: _replace(f, "rgba", f["rgba"][()].astype(np.float32)), "'rgba' has dtype float32, expected uint8"),
    (lambda f: _replace(f, "frames", f["frames"][()][::-1].copy()), "differ from the manifest"),
])
def test_dataset_refuses_what_verify_refuses(converted_copy, edit, match):
    from deliffas.data.dataset import ShardDataset
    from deliffas.data.shards import ShardReadError

    _edit_shard(converted_copy, "shards/training-00000.h5", edit)
    ds = ShardDataset(converted_copy, split="train", temporal_window=2, protocol="all")
    with pytest.raises(ShardReadError, match=rf"training-00000\.h5: cannot read frame \d+ \(.*{match}"):
        ds[0]
