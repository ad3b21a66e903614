"""Readers/writers of deliffas.io.formats.dynacap.character on the real sample and on malformed files."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from deliffas.io.formats.dynacap import character as dc
from deliffas.io.formats.dynacap import skeleton as skeleton_io
from deliffas.io.formats.dynacap.calibration import read_calibration, write_calibration
from deliffas.io.formats.dynacap.meshes import MeshSequence, read_meshes, write_meshes
from deliffas.io.cameras import Camera
from deliffas.io.formats.dynacap.character import DynaCapFormatError


# ---------------------------------------------------------------- real sample: counts and decoding
def test_sample_counts(sample_character, sample_motion):
    c = sample_character
    assert c.skeleton.num_joints == 173
    assert c.skeleton.num_dofs == 107
    assert c.mesh.num_verts == 5514
    assert c.mesh.num_faces == 11024
    assert len(c.mesh.uvs) == 5964
    assert sample_motion.num_frames == 1000
    assert sample_motion.frames[0] == 0 and sample_motion.frames[-1] == 999
    assert len(c.skin.bones) == 69
    assert c.graph is not None and c.graph.num_verts == 852 and c.graph.num_faces == 1700
    assert c.texture is not None and c.texture.name == "ddc.png"
    assert set(np.unique(c.segmentation)) == {0, 18}
    assert np.bincount(c.hand_segmentation).tolist() == [5140, 191, 183]


def test_skin_glued_tokens_decoded(sample_character):
    skin = sample_character.skin
    sums = skin.weights.sum(1)
    np.testing.assert_allclose(sums, 1.0, atol=2.5e-6)
    # vertex 0 reads "0 0 0.3464430 9 ..." in the file: the glued index 0 must be gone
    assert skin.weights[0, 0] == pytest.approx(0.346443)
    assert skin.weights[5512, 0] == pytest.approx(0.372668)
    assert (skin.indices >= 0).all() and skin.indices.max() == 67
    assert (np.diff(skin.weights, axis=1) <= 1e-12).all(), "influences sorted by decreasing weight"
    # e-notation weights like 2.69467e-050 decode to ~2.7e-5, never ~1e-50
    assert skin.weights.min() > 1e-12


def test_naive_parse_would_be_wrong(sample_dir):
    """Guard: the glued decoding matters (naively split weights do not sum to 1 on every line)."""
    lines = (sample_dir / "ddc.skin").read_text().splitlines()[4:]
    worst = max(abs(sum(float(w) for w in ln.split()[2::2]) - 1) for ln in lines)
    assert worst > 1e-4


def test_prefix_and_bone_rules(sample_character):
    sk = sample_character.skeleton
    W_prefix, W_exact = sk.dof_weights("prefix"), sk.dof_weights("exact")
    differing = [sk.dofs[i].name for i in np.nonzero(np.abs(W_prefix - W_exact).sum(1))[0]]
    assert len(differing) == 10 and all("flex1" in n for n in differing)
    bone = {b: sk.joints[sk.bone_joint_index(b)].name for b in ("Head", "LeftForeArm", "LeftFoot", "LeftArm")}
    assert bone == {"Head": "HeadEE", "LeftForeArm": "LeftForeArmRoll", "LeftFoot": "LeftFootEE", "LeftArm": "LeftArmScale"}


# ---------------------------------------------------------------- round trips
@pytest.mark.parametrize("crlf", [False, True])
def test_character_round_trip(sample_character, tmp_path, crlf):
    c = sample_character
    path = dc.write_character(tmp_path / "out", c, name="ddc", crlf=crlf)
    if crlf:
        assert b"\r\n" in (tmp_path / "out" / "ddc.skeleton").read_bytes()
    r = dc.read_character(path)
    assert r.skeleton.joint_names == c.skeleton.joint_names
    for a, b in zip(r.skeleton.joints, c.skeleton.joints):
        assert a.type == b.type and a.parent == b.parent and a.scale == b.scale
        np.testing.assert_array_equal(a.offset, b.offset)
        np.testing.assert_array_equal(a.axis, b.axis)
    assert r.skeleton.dofs == c.skeleton.dofs
    assert len(r.skeleton.markers) == 97 and r.skeleton.markers == c.skeleton.markers
    np.testing.assert_allclose(r.mesh.verts, c.mesh.verts, atol=5e-7)
    np.testing.assert_array_equal(r.mesh.faces, c.mesh.faces)
    np.testing.assert_array_equal(r.mesh.face_uvs, c.mesh.face_uvs)
    np.testing.assert_allclose(r.mesh.uvs, c.mesh.uvs, atol=5e-7)
    np.testing.assert_array_equal(r.skin.indices, c.skin.indices)
    np.testing.assert_array_equal(r.skin.weights, c.skin.weights)
    np.testing.assert_array_equal(r.rest_dofs, c.rest_dofs)
    np.testing.assert_array_equal(r.segmentation, c.segmentation)
    np.testing.assert_array_equal(r.hand_segmentation, c.hand_segmentation)
    np.testing.assert_allclose(r.graph.verts, c.graph.verts, atol=5e-7)
    assert r.texture is not None and r.texture.read_bytes() == c.texture.read_bytes()


def test_motion_round_trip(sample_motion, tmp_path):
    dc.write_motion(tmp_path / "m.motion", sample_motion)
    r = dc.read_motion(tmp_path / "m.motion", num_dofs=107)
    np.testing.assert_array_equal(r.frames, sample_motion.frames)
    np.testing.assert_allclose(r.dofs, sample_motion.dofs, rtol=1e-9, atol=0)


def test_meshes_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    seq = MeshSequence(np.arange(5, 9), np.round(rng.normal(0, 500, (4, 7, 3)), 1).astype(np.float32))
    write_meshes(tmp_path / "a.meshes", seq)
    r = read_meshes(tmp_path / "a.meshes", num_verts=7)
    np.testing.assert_array_equal(r.frames, seq.frames)
    np.testing.assert_allclose(r.verts, seq.verts, atol=1e-3)
    (tmp_path / "b.meshes").write_text("Skeletool Meshes file v2.0\n" + "\n".join(" ".join(map(str, v.ravel())) for v in seq.verts) + "\n")
    r2 = read_meshes(tmp_path / "b.meshes")
    np.testing.assert_array_equal(r2.frames, np.arange(4))


def _camera(name="0", w=1285, h=940):
    K = np.array([[766.3206, 0, 635.1871], [0, 765.7619, 448.8466], [0, 0, 1.0]])
    E = np.array([[-0.453446, -0.3859819, -0.8033708, 703.8229],
                  [0.6526945, -0.7576083, -0.004404724, 150.761],
                  [-0.6069403, -0.5263531, 0.5954627, 4868.044], [0, 0, 0, 1.0]])
    return Camera(name, K, E, w, h, (14.1864, 10.3776), 0.0)


def test_calibration_round_trip_and_reference_block(tmp_path):
    text = """Skeletool Camera Calibration File V1.0
name        0
sensor      14.1864 10.3776
size        1285 940
animated    0
intrinsic   766.3206 0 635.1871 0 0 765.7619 448.8466 0 0 0 1 0 0 0 0 1 
extrinsic   -0.453446 -0.3859819 -0.8033708 703.8229 0.6526945 -0.7576083 -0.004404724 150.761 -0.6069403 -0.5263531 0.5954627 4868.044 0 0 0 1 
radial      0
"""
    (tmp_path / "c.calibration").write_text(text)
    cams = read_calibration(tmp_path / "c.calibration")
    assert len(cams) == 1 and cams[0].width == 1285 and cams[0].height == 940
    # formats doc 1.9: camera centre ≈ (3175, 2948, -2333) mm
    np.testing.assert_allclose(cams[0].center, [3175, 2948, -2333], atol=2)
    write_calibration(tmp_path / "d.calibration", cams + [_camera("1")], crlf=True)
    back = read_calibration(tmp_path / "d.calibration")
    assert [c.name for c in back] == ["0", "1"]
    for a, b in zip(back, cams + [_camera("1")]):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.world_to_cam, b.world_to_cam)
        assert a.sensor == b.sensor


def test_segmentation_round_trip(tmp_path):
    labels = np.array([0, 18, 5, 12, 0])
    dc.write_segmentation(tmp_path / "s.txt", labels, crlf=True)
    np.testing.assert_array_equal(dc.read_segmentation(tmp_path / "s.txt", 5), labels)


# ---------------------------------------------------------------- malformed files
def _copy_sample(sample_dir: Path, dst: Path) -> Path:
    for f in sample_dir.iterdir():
        if f.is_file():
            shutil.copy(f, dst / f.name)
    return dst


def _expect_error(fn, path, line, match):
    with pytest.raises(DynaCapFormatError, match=match) as info:
        fn(path)
    assert info.value.path == str(path)
    if line is not None:
        assert info.value.line == line
    assert isinstance(info.value, ValueError)
    return info.value


def test_truncated_skeleton(sample_dir, tmp_path):
    lines = (sample_dir / "ddc.skeleton").read_text().splitlines()
    p = tmp_path / "t.skeleton"
    p.write_text("\n".join(lines[:100]) + "\n")
    _expect_error(skeleton_io.read_skeleton, p, 2, "exceeds")


def test_wrong_token_count_skeleton(sample_dir, tmp_path):
    lines = (sample_dir / "ddc.skeleton").read_text().splitlines()
    lines[4] = lines[4] + " 7"
    p = tmp_path / "t.skeleton"
    p.write_text("\n".join(lines) + "\n")
    _expect_error(skeleton_io.read_skeleton, p, 5, "10 tokens")


def test_unknown_joint_in_dof(sample_dir, tmp_path):
    text = (sample_dir / "ddc.skeleton").read_text().replace("Root_tx                    1000", "NoSuchJoint 1000", 1)
    p = tmp_path / "t.skeleton"
    p.write_text(text)
    err = _expect_error(skeleton_io.read_skeleton, p, None, "unknown joint 'NoSuchJoint'")
    assert err.line == 278


def test_nan_in_motion_and_wrong_dof_count(sample_dir, tmp_path):
    lines = (sample_dir / "skeletoolToGTPose" / "poseAngles.motion").read_text().splitlines()[:5]
    p = tmp_path / "m.motion"
    bad = lines.copy()
    toks = bad[3].split()
    toks[5] = "nan"
    bad[3] = " ".join(toks)
    p.write_text("\n".join(bad) + "\n")
    _expect_error(lambda q: dc.read_motion(q, 107), p, 4, "finite DOF values, got NaN/inf in column 4")
    short = lines.copy()
    short[2] = " ".join(short[2].split()[:-1])
    p.write_text("\n".join(short) + "\n")
    _expect_error(lambda q: dc.read_motion(q, 107), p, 3, "107 DOF values, got 106")
    p.write_text("\n".join(lines) + "\n")
    _expect_error(lambda q: dc.read_motion(q, 60), p, 2, "60 DOF values, got 107")


def test_skin_bad_inputs(sample_dir, tmp_path):
    lines = (sample_dir / "ddc.skin").read_text().splitlines()
    p = tmp_path / "s.skin"
    p.write_text("\n".join(lines[:100]) + "\n")
    _expect_error(lambda q: dc.read_skin(q, num_verts=5514), p, None, r"expected 5514 vertex lines \(mesh vertices\), got 96")
    bad = lines.copy()
    bad[10] = bad[10] + " 3"
    p.write_text("\n".join(bad) + "\n")
    _expect_error(dc.read_skin, p, 11, "pairs")
    bad = lines.copy()
    bad[10] = "99 " + " ".join(bad[10].split()[1:])
    p.write_text("\n".join(bad) + "\n")
    _expect_error(dc.read_skin, p, 11, "vertex index 6")


def test_obj_bad_inputs(tmp_path):
    p = tmp_path / "m.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    _expect_error(dc.read_obj, p, 4, "out of range")
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 inf\nf 1 2 3\n")
    _expect_error(dc.read_obj, p, 3, "finite")
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3 4\n")
    _expect_error(dc.read_obj, p, 5, "triangle")
    p.write_text("v 0 0\n")
    _expect_error(dc.read_obj, p, 1, "3 or 4 or 6 or 7 numbers")


def test_obj_keeps_vertex_order_and_seams(sample_character):
    m = sample_character.mesh
    assert m.verts.shape == (5514, 3)
    # 444 vertices lie on UV seams: more uv indices than vertices, never split vertices
    corners_per_vertex = {}
    for v, t in zip(m.faces.ravel(), m.face_uvs.ravel()):
        corners_per_vertex.setdefault(int(v), set()).add(int(t))
    assert sum(len(s) > 1 for s in corners_per_vertex.values()) == 444
    np.testing.assert_allclose(m.verts[0], [485.561890, 1369.734497, 126.120674])


def test_missing_referenced_file(sample_dir, tmp_path):
    d = _copy_sample(sample_dir, tmp_path)
    (d / "ddc.skin").unlink()
    _expect_error(dc.read_character, d / "ddc.character", None, "'skin' file .*does not exist")


def test_skin_mesh_vertex_mismatch(sample_dir, tmp_path):
    d = _copy_sample(sample_dir, tmp_path)
    lines = (d / "ddc.skin").read_text().splitlines()
    (d / "ddc.skin").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(DynaCapFormatError, match="expected 5514 vertex lines"):
        dc.read_character(d / "ddc.character")


def test_missing_file_and_binary(tmp_path):
    _expect_error(skeleton_io.read_skeleton, tmp_path / "none.skeleton", 0, "not found")
    p = tmp_path / "b.motion"
    p.write_bytes(b"Skeletool Motion File V1.0\n0 1 2\x00\x01\n")
    with pytest.raises(DynaCapFormatError):
        dc.read_motion(p)


def test_bad_calibration(tmp_path):
    p = tmp_path / "c.calibration"
    p.write_text("Skeletool Camera Calibration File V1.0\nname 0\nsize 10 10\nintrinsic 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0\n")
    _expect_error(read_calibration, p, 4, "16 numbers")
    p.write_text("Skeletool Camera Calibration File V1.0\nname 0\nsize 10 10\n")
    _expect_error(read_calibration, p, 2, "lacks its 'intrinsic'")
    p.write_text("Skeletool Camera File\n")
    _expect_error(read_calibration, p, 1, "header")


_ANIMATED = """Skeletool Camera Calibration File V1.0
name        0
sensor      14.1864 10.3776
size        64 48
animated    1
frame 0
intrinsic   50 0 32 0 0 50 24 0 0 0 1 0 0 0 0 1
extrinsic   1 0 0 0 0 1 0 0 0 0 1 3000 0 0 0 1
radial      0
frame 1
extrinsic   1 0 0 10 0 1 0 0 0 0 1 3000 0 0 0 1
frame 2
intrinsic   60 0 32 0 0 60 24 0 0 0 1 0 0 0 0 1
extrinsic   1 0 0 20 0 1 0 0 0 0 1 3000 0 0 0 1
"""


def test_animated_calibration_one_camera_per_frame_block(tmp_path):
    p = tmp_path / "a.calibration"
    p.write_text(_ANIMATED)
    cams = read_calibration(p)
    assert [c.name for c in cams] == ["0@0", "0@1", "0@2"]
    assert [c.t[0] for c in cams] == [0, 10, 20]
    assert [c.K[0, 0] for c in cams] == [50, 50, 60]  # frame 1 keeps frame 0's intrinsic


def test_animated_frame_without_extrinsic_is_refused(tmp_path):
    p = tmp_path / "a.calibration"
    p.write_text(_ANIMATED.replace("extrinsic   1 0 0 10 0 1 0 0 0 0 1 3000 0 0 0 1\n", ""))
    _expect_error(read_calibration, p, 10, r"camera '0' frame 1 lacks its 'extrinsic' line")
    p.write_text(_ANIMATED.replace("frame 2", "frame 1"))
    _expect_error(read_calibration, p, 12, "has frame 1 twice")
    p.write_text(_ANIMATED.replace("animated    1", "animated    0"))
    _expect_error(read_calibration, p, 6, "not 'animated 1'")


@pytest.mark.parametrize("R, what", [("2 0 0 0 0 2 0 0 0 0 2", "scaled"), ("-1 0 0 0 0 1 0 0 0 0 1", "mirrored")])
def test_extrinsic_must_be_a_rotation(tmp_path, R, what):
    text = _ANIMATED.split("animated")[0] + "animated    0\nintrinsic   50 0 32 0 0 50 24 0 0 0 1 0 0 0 0 1\n"
    p = tmp_path / f"{what}.calibration"
    p.write_text(text + f"extrinsic   {R} 3000 0 0 0 1\n")
    _expect_error(read_calibration, p, 2, r"R must be a rotation")


_SKIN = "Skeletool character skinning file V1.0\nbones:\n a b\nvertex weights:\n0 0 1.0\n1 0 0.5 1 0.5\n{row2}\n"


@pytest.mark.parametrize("row2, match", [
    ("2 0 0.0 1 0.0", "sum to 1 .*got 0"),
    ("2 0 -0.5 1 1.5", "weight >= 0, got -0.5"),
    ("2 0 2.5 1 2.5", "sum to 1 .*got 5"),
])
def test_skin_weights_must_be_a_partition_of_one(tmp_path, row2, match):
    p = tmp_path / "bad.skin"
    p.write_text(_SKIN.format(row2=row2))
    _expect_error(dc.read_skin, p, 7, match)
    p.write_text(_SKIN.format(row2="2 0 0.25 1 0.7505"))  # rounding within 1e-3 is accepted
    assert dc.read_skin(p).weights[2].sum() == pytest.approx(1.0005)


_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n{face}\n"


@pytest.mark.parametrize("face, line, match", [
    ("f 1/-1 2/-2 3/-4", 7, r"relative vt index -4 counts back past the first of the 3"),
    ("f -1/1 -2/2 -5/3", 7, r"relative v index -5"),
    ("f 1/1 2 3/3", 7, "face without a uv index in a file with 3 'vt' lines"),
])
def test_obj_relative_and_missing_uv_indices(tmp_path, face, line, match):
    p = tmp_path / "bad.obj"
    p.write_text(_OBJ.format(face=face))
    _expect_error(dc.read_obj, p, line, match)
    p.write_text(_OBJ.format(face="f -3/-3 -2/-2 -1/-1"))  # relative indices resolve to the last three
    obj = dc.read_obj(p)
    assert obj.faces.tolist() == [[0, 1, 2]] and obj.face_uvs.tolist() == [[0, 1, 2]]
