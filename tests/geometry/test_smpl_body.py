"""The procedural SMPL-layout body: its layout, its files, and SMPLTemplate against the smplx package on it."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
import torch

from deliffas.geometry.smpl_body import (
    SMPL_JOINT_NAMES, SMPL_PARENTS, make_procedural_smpl, procedural_smpl, procedural_smpl_joints)
from deliffas.geometry.templates import SMPLTemplate, build_template, smpl_spec
from deliffas.io.body_models.smpl import SMPLModelError, load_smpl_model, write_smpl_model

OFFICIAL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]


@pytest.fixture(scope="module")
def body_files(tmp_path_factory):
    """(npz, uv obj) of the seed-0 body, written once for the module."""
    npz = make_procedural_smpl(tmp_path_factory.mktemp("smpl_body"), seed=0, target_verts=1500)
    return npz, npz.parent / "smpl_procedural_uv.obj"


@pytest.fixture(scope="module")
def body(body_files):
    return load_smpl_model(body_files[0])


def _random_params(rng: np.random.Generator, n: int, pose_std: float = 0.35) -> np.ndarray:
    transl = rng.normal(0, 0.3, (n, 3))
    pose = rng.normal(0, pose_std, (n, 72))
    pose[:, :3] = rng.normal(0, 1.0, (n, 3))
    betas = rng.normal(0, 1.0, (n, 10))
    return np.concatenate([transl, pose, betas], axis=1)


def test_layout(body):
    V = body.num_verts
    assert 1300 <= V <= 1700 and body.faces.shape == (2 * V - 4, 3), "closed genus-0 mesh near the budget"
    assert body.shapedirs.shape == (V, 3, 10) and body.posedirs.shape == (V, 3, 207)
    assert body.J_regressor.shape == (24, V) and body.weights.shape == (V, 24)
    np.testing.assert_array_equal(body.parents, OFFICIAL_PARENTS)
    np.testing.assert_array_equal(SMPL_PARENTS, OFFICIAL_PARENTS)
    assert SMPL_JOINT_NAMES[:4] == ("pelvis", "l_hip", "r_hip", "spine1") and SMPL_JOINT_NAMES[-1] == "r_hand"
    np.testing.assert_allclose(body.J_regressor.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(body.weights.sum(1), 1.0, atol=1e-12)
    assert body.J_regressor.min() >= 0 and body.weights.min() >= 0
    assert (body.weights.max(0) > 0.2).all(), "every joint drives some of the skin"


def test_conventions_and_regressed_joints(body):
    v = body.v_template
    joints = procedural_smpl_joints(0)
    np.testing.assert_allclose(body.J_regressor @ v, joints, atol=1e-9)  # metres
    height = v[:, 1].max() - v[:, 1].min()
    assert 1.6 < height < 1.9, "metres, y-up"
    name = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    assert joints[name["l_hip"], 0] > 0 > joints[name["r_hip"], 0], "the body's left at +x"
    assert joints[name["l_foot"], 2] > joints[name["l_ankle"], 2], "toes point +z (facing +z)"
    assert abs(joints[name["l_wrist"], 1] - joints[name["l_shoulder"], 1]) < 0.01, "T-pose"
    assert np.linalg.norm(joints[name["pelvis"]]) < 1e-9


def test_blend_shapes_are_small_meaningful_and_nonzero(body):
    sd = body.shapedirs
    per_beta = np.linalg.norm(sd, axis=1).max(0)  # (10,) largest vertex motion per unit beta, metres
    assert ((per_beta > 0.005) & (per_beta < 0.06)).all(), per_beta
    y = body.v_template[:, 1]
    grown = body.v_template + sd[:, :, 0]
    assert np.ptp(grown[:, 1]) > np.ptp(y) * 1.02, "beta 0 makes the body taller"
    assert np.abs(body.posedirs).max() > 1e-3 and np.abs(body.posedirs).max() < 0.01


def test_deterministic_for_a_seed(body):
    again = procedural_smpl(0, target_verts=1500)
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "faces"):
        np.testing.assert_allclose(getattr(again, key), getattr(body, key), atol=1e-12, err_msg=key)
    assert not np.allclose(procedural_smpl_joints(1), procedural_smpl_joints(0)), "another seed, another body"


def test_files_load_through_the_user_path(body_files, body, tmp_path):
    npz, obj = body_files
    template = build_template(smpl_spec(npz, uv_obj=obj))
    assert template.num_verts == body.num_verts and template.face_uvs.shape == template.faces.shape
    assert 0 <= float(template.uvs.min()) and float(template.uvs.max()) <= 1
    with np.load(npz) as z:
        assert set(z.files) == {"v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f"}
        assert z["kintree_table"][0, 0] == 4294967295
    copy = tmp_path / "copy.npz"
    write_smpl_model(copy, body)
    again = load_smpl_model(copy)
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "parents", "faces"):
        np.testing.assert_array_equal(getattr(again, key), getattr(body, key), err_msg=key)
    assert not list(tmp_path.glob(".*tmp-*")), "no temporary file left"
    with pytest.raises(SMPLModelError, match=r"bad\.pkl.*\.npz"):
        write_smpl_model(tmp_path / "bad.pkl", body)


def test_pose_blend_shapes_are_on(body):
    params = torch.tensor(_random_params(np.random.default_rng(1), 2))
    posed = SMPLTemplate(body, dtype=torch.float64).pose(params)
    no_correctives = dataclasses.replace(body, posedirs=np.zeros_like(body.posedirs))
    flat = SMPLTemplate(no_correctives, dtype=torch.float64).pose(params)
    assert (posed - flat).norm(dim=-1).max() > 2.0, "mm: the pose correctives move vertices"


def test_smpl_template_equals_smplx(body_files, body, tmp_path):
    smplx = pytest.importorskip(
        "smplx", reason="smplx (test-only) is not installed: pip install smplx==0.1.28 --no-deps")
    from smplx.vertex_ids import vertex_ids

    with np.load(body_files[0]) as z:  # the same arrays as a plain-numpy pickle, the form smplx reads
        arrays = {k: z[k] for k in z.files}
    pkl = tmp_path / "SMPL_NEUTRAL.pkl"
    with open(pkl, "wb") as fh:
        pickle.dump(arrays, fh, protocol=2)
    assert load_smpl_model(pkl).num_verts == body.num_verts, "the pickle also loads in deliffas"
    # smplx's extra keypoints index SMPL's 6890 vertices; point them at vertex 0 (they are not compared)
    ids = {k: 0 for k in vertex_ids["smplh"]}
    layer = smplx.SMPL(str(pkl), num_betas=10, dtype=torch.float64, vertex_ids=ids)
    ours = SMPLTemplate(body_files[0], num_betas=10, dtype=torch.float64)
    params = torch.tensor(_random_params(np.random.default_rng(2), 4))
    with torch.no_grad():
        out = layer(betas=params[:, 75:], global_orient=params[:, 3:6], body_pose=params[:, 6:75],
                    transl=params[:, :3])
        verts = ours.pose(params)
    # smplx stores its buffers in float32 (to_np) even with dtype=float64: compare to that rounding
    err = (out.vertices * 1000 - verts).abs().max().item()
    assert err < 1e-3, f"max |smplx - SMPLTemplate| = {err:.2e} mm"


def test_pose_cli_equals_smplx(body_files, tmp_path):
    """``deliffas pose MODEL.npz MOTION.npz --frame N --out F.ply`` gives smplx's SMPL vertices x 1000."""
    smplx = pytest.importorskip(
        "smplx", reason="smplx (test-only) is not installed: pip install smplx==0.1.28 --no-deps")
    import trimesh
    from smplx.vertex_ids import vertex_ids

    from deliffas.cli import main
    from deliffas.io.body_models.amass import SMPLMotion, write_smpl_motion

    with np.load(body_files[0]) as z:
        arrays = {k: z[k] for k in z.files}
    pkl = tmp_path / "SMPL_NEUTRAL.pkl"
    with open(pkl, "wb") as fh:
        pickle.dump(arrays, fh, protocol=2)
    layer = smplx.SMPL(str(pkl), num_betas=10, dtype=torch.float64, vertex_ids={k: 0 for k in vertex_ids["smplh"]})
    params = _random_params(np.random.default_rng(5), 3)
    params[:, 75:] = params[0, 75:]  # one shape per motion
    motion = tmp_path / "m.npz"
    write_smpl_motion(motion, SMPLMotion(params[:, 3:75], params[:, :3], params[0, 75:], fps=30.0))
    for frame in range(3):
        out = tmp_path / f"f{frame}.ply"
        assert main(["pose", str(body_files[0]), str(motion), "--frame", str(frame), "--out", str(out)]) == 0
        ours = np.asarray(trimesh.load(out, process=False).vertices)
        p = torch.tensor(params[frame:frame + 1])
        with torch.no_grad():
            ref = layer(betas=p[:, 75:], global_orient=p[:, 3:6], body_pose=p[:, 6:75], transl=p[:, :3]).vertices
        err = np.abs(ref[0].numpy() * 1000 - ours).max()
        assert err < 1e-3, f"frame {frame}: max |smplx - deliffas pose| = {err:.2e} mm"


@pytest.mark.parametrize("case, match", [
    ("missing_key", "missing arrays ['posedirs']"),
    ("wrong_shape", "'weights' expected shape"),
    ("pose_length", "poses"),
    ("nan", "trans"),
])
def test_bad_smpl_inputs_are_one_error_line(body_files, tmp_path, capsys, case, match):
    from deliffas.cli import main

    with np.load(body_files[0]) as z:
        arrays = {k: z[k] for k in z.files}
    poses, trans = np.zeros((2, 72)), np.zeros((2, 3))
    if case == "missing_key":
        del arrays["posedirs"]
    elif case == "wrong_shape":
        arrays["weights"] = arrays["weights"][:, :20]
    elif case == "pose_length":
        poses = np.zeros((2, 70))
    elif case == "nan":
        trans[1, 2] = np.nan
    model, motion = tmp_path / "model.npz", tmp_path / "motion.npz"
    np.savez(model, **arrays)
    np.savez(motion, poses=poses, trans=trans, betas=np.zeros(10))
    assert main(["pose", str(model), str(motion), "--out", str(tmp_path / "o.ply")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error:" in err[0] and match in err[0], err
    assert str(model if case in ("missing_key", "wrong_shape") else motion) in err[0]
    assert not (tmp_path / "o.ply").exists()
