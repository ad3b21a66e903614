"""AMASS-style SMPL motions: write -> read round trip, SMPL-H/X poses, every layout error."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.io.body_models.amass import SMPLMotion, SMPLMotionError, read_smpl_motion, write_smpl_motion


def _motion(n: int = 5, pose_dim: int = 72, num_betas: int = 16, seed: int = 0) -> SMPLMotion:
    rng = np.random.default_rng(seed)
    return SMPLMotion(rng.normal(0, 0.3, (n, pose_dim)), rng.normal(0, 1, (n, 3)), rng.normal(0, 1, num_betas),
                      fps=120.0, gender="female")


def _save(path, **arrays):
    np.savez(path, **arrays)
    return path


def _valid(n: int = 4) -> dict:
    rng = np.random.default_rng(1)
    return {"poses": rng.normal(0, 0.2, (n, 156)), "trans": rng.normal(0, 1, (n, 3)), "betas": np.zeros(16),
            "mocap_framerate": np.array(60.0), "gender": np.array("male")}


@pytest.mark.parametrize("pose_dim", [72, 156, 165])
def test_round_trip(tmp_path, pose_dim):
    m = _motion(pose_dim=pose_dim)
    p = tmp_path / "walk_poses.npz"
    write_smpl_motion(p, m)
    back = read_smpl_motion(p)
    np.testing.assert_array_equal(back.poses, m.poses)
    np.testing.assert_array_equal(back.trans, m.trans)
    np.testing.assert_array_equal(back.betas, m.betas)
    assert back.fps == 120.0 and back.gender == "female" and back.num_frames == 5
    assert not list(tmp_path.glob(".*tmp-*")), "no temporary file left"
    no_meta = SMPLMotion(m.poses, m.trans, m.betas)
    write_smpl_motion(p, no_meta)
    assert read_smpl_motion(p).fps is None and read_smpl_motion(p).gender is None


def test_amass_file_with_smplx_frame_rate_key(tmp_path):
    d = _valid()
    d["mocap_frame_rate"] = d.pop("mocap_framerate")
    d["dmpls"] = np.zeros((4, 8))
    m = read_smpl_motion(_save(tmp_path / "smplx.npz", **d))
    assert m.fps == 60.0 and m.gender == "male" and m.poses.shape == (4, 156)


def test_smplh_pose_keeps_the_shared_body_joints():
    m = _motion(pose_dim=156)
    pose = m.smpl_pose
    assert pose.shape == (5, 72)
    np.testing.assert_array_equal(pose[:, :66], m.poses[:, :66])
    assert not pose[:, 66:].any(), "SMPL's l_hand/r_hand are zero, not SMPL-H's first finger joints"
    smpl = _motion(pose_dim=72)
    np.testing.assert_array_equal(smpl.smpl_pose, smpl.poses)


@pytest.mark.parametrize("change, match", [
    (lambda d: d.pop("poses"), r"missing keys \['poses'\]"),
    (lambda d: d.pop("trans"), r"missing keys \['trans'\]"),
    (lambda d: d.pop("betas"), r"missing keys \['betas'\]"),
    (lambda d: d.update(poses=np.zeros((4, 70))), r"'poses' expected shape \(N, 72\) or \(N, 3k\).*\(4, 70\)"),
    (lambda d: d.update(poses=np.zeros((4, 69))), r"'poses' expected .*k >= 24.*\(4, 69\)"),
    (lambda d: d.update(poses=np.zeros(72)), r"'poses' expected .*\(72,\)"),
    (lambda d: d.update(trans=np.zeros((4, 2))), r"'trans' expected shape \(N, 3\), got \(4, 2\)"),
    (lambda d: d.update(trans=np.zeros((3, 3))), r"'trans' has 3 frames but 'poses' has 4"),
    (lambda d: d.update(betas=np.zeros(8)), r"'betas' expected shape \(NB,\) with NB >= 10, got \(8,\)"),
    (lambda d: d["poses"].__setitem__((1, 5), np.nan), r"'poses' holds 1 NaN or inf"),
    (lambda d: d["trans"].__setitem__((0, 0), np.inf), r"'trans' holds 1 NaN or inf"),
    (lambda d: d["betas"].__setitem__(3, np.nan), r"'betas' holds 1 NaN or inf"),
    (lambda d: d.update(poses=np.array([["a"] * 72] * 4)), r"'poses' expected an array of real numbers, got dtype <U1"),
    (lambda d: d.update(mocap_framerate=np.array(-1.0)), r"'mocap_framerate' expected one positive frame rate"),
])
def test_bad_files_name_file_and_key(tmp_path, change, match):
    d = _valid()
    change(d)
    p = _save(tmp_path / "bad_motion.npz", **d)
    with pytest.raises(SMPLMotionError, match=r"bad_motion\.npz: " + match):
        read_smpl_motion(p)


def test_pickled_arrays_are_refused_and_missing_file(tmp_path):
    d = _valid()
    d["poses"] = np.array([object()] * 3, dtype=object)
    p = _save(tmp_path / "pickled.npz", **d)
    with pytest.raises(SMPLMotionError, match=r"pickled\.npz: 'poses' expected an array of real numbers, got dtype object"):
        read_smpl_motion(p)
    with pytest.raises(FileNotFoundError, match="nowhere.npz"):
        read_smpl_motion(tmp_path / "nowhere.npz")
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(SMPLMotionError, match=r"text\.npz: 'NPZ' expected an \.npz \(zip\) archive"):
        read_smpl_motion(tmp_path / "text.npz")


def test_record_and_writer_checks(tmp_path, unchecked):
    with unchecked(), pytest.raises(SMPLMotionError, match=r"SMPLMotion: 'trans' has 2 frames but 'poses' has 3"):
        SMPLMotion(np.zeros((3, 72)), np.zeros((2, 3)), np.zeros(10))
    with unchecked(), pytest.raises(SMPLMotionError, match=r"motion\.pkl: write_smpl_motion writes \.npz"):
        write_smpl_motion(tmp_path / "motion.pkl", _motion())
