"""Forward kinematics, LBS/DQS and DDCTemplate posing on the real sample and small oracles."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from deliffas.geometry.skeleton import axis_angle_to_matrix
from deliffas.geometry.skinning import dqs, lbs, matrix_to_quaternion, quaternion_to_matrix
from deliffas.geometry.templates import DDCTemplate


def _fk_reference(skel, dofs):
    """Loop-based FK oracle: T_j = T_parent · Translate(scale·offset) · Motion(p_j)."""
    W = skel.dof_weights("prefix")
    p = dofs @ W
    names = {j.name: i for i, j in enumerate(skel.joints)}
    G = [None] * skel.num_joints
    for i, j in enumerate(skel.joints):  # parents precede children in the sample
        L = np.eye(4)
        L[:3, 3] = j.offset * j.scale
        M = np.eye(4)
        if j.type == "revolute":
            a = j.axis / np.linalg.norm(j.axis)
            K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            M[:3, :3] = np.eye(3) + np.sin(p[i]) * K + (1 - np.cos(p[i])) * K @ K
        else:
            M[:3, 3] = p[i] * j.axis
        parent = names.get(j.parent)
        G[i] = (G[parent] if parent is not None else np.eye(4)) @ L @ M
    return np.stack(G)


def test_fk_matches_loop_reference(sample_character, sample_motion, device):
    t = DDCTemplate(sample_character, dtype=torch.float64).to(device)
    x = sample_motion.dofs[[0, 500, 999]]
    G = t.fk(torch.tensor(x, device=device)).cpu().numpy()
    for k in range(3):
        np.testing.assert_allclose(G[k], _fk_reference(sample_character.skeleton, x[k]), atol=1e-8)


def test_fk_sanity_rest_pose(sample_character):
    t = DDCTemplate(sample_character, dtype=torch.float64)
    names = sample_character.skeleton.joint_names
    G = t.fk(torch.tensor(sample_character.rest_dofs)[None])[0].numpy()
    # formats doc 1.3: root chain at (440.3, 1341.0, 164.7) mm, HeadEE y≈1744, foot end-effectors y≈10–12
    np.testing.assert_allclose(G[names.index("Root_tz"), :3, 3], [440.3, 1341.0, 164.7], atol=0.1)
    assert G[names.index("HeadEE"), 1, 3] == pytest.approx(1744, abs=2)
    for foot in ("LeftToeBaseEE" if "LeftToeBaseEE" in names else "LeftFootEE", "RightFootEE"):
        assert 0 < G[names.index(foot), 1, 3] < 60
    ys = sample_character.mesh.verts[:, 1]
    assert ys.min() == pytest.approx(1.2, abs=0.5) and ys.max() == pytest.approx(1765, abs=2)


def test_rest_pose_reproduces_template(sample_character):
    # LBS scales by the weight sum (1 ± 2e-6 in the file, ~2000 mm coordinates) -> 5e-3 mm; DQS normalises.
    for dtype, mode, tol in ((torch.float64, "dqs", 1e-9), (torch.float64, "lbs", 5e-3),
                             (torch.float32, "dqs", 1e-3), (torch.float32, "lbs", 5e-3)):
        t = DDCTemplate(sample_character, dtype=dtype)
        v = t.pose(torch.tensor(sample_character.rest_dofs)[None], mode)[0]
        assert (v - t.rest_verts).abs().max().item() < tol, (dtype, mode)


def test_all_frames_one_batched_call(sample_character, sample_motion):
    t = DDCTemplate(sample_character)
    x = torch.tensor(sample_motion.dofs, dtype=torch.float32)
    with torch.no_grad():
        v = t.pose(x)
    assert v.shape == (1000, 5514, 3) and torch.isfinite(v).all()
    names = sample_character.skeleton.joint_names
    G = t.fk(x)
    head = G[:, names.index("HeadEE"), 1, 3]
    feet = torch.minimum(G[:, names.index("LeftFootEE"), 1, 3], G[:, names.index("RightFootEE"), 1, 3])
    assert 1500 < head.median() < 1850, "head height of a standing person"
    assert -20 < feet.median() < 60, "the lower foot stays near the floor"
    # the body's vertical extent stays human: 1.5-1.9 m
    extent = v[..., 1].amax(1) - v[..., 1].amin(1)
    assert 1300 < extent.median() < 1900


def test_lbs_dqs_agree_on_mild_poses(sample_character):
    t = DDCTemplate(sample_character, dtype=torch.float64)
    rng = np.random.default_rng(0)
    x = sample_character.rest_dofs + np.concatenate([np.zeros(6), rng.normal(0, 0.03, 87), np.zeros(14)])
    x = torch.tensor(x)[None]
    d = (t.pose(x, "lbs") - t.pose(x, "dqs")).norm(dim=-1)
    assert d.max() < 2.0, f"mild pose: LBS and DQS should agree within 2 mm, got {d.max():.2f}"
    assert d.max() > 1e-6, "they are different algorithms"


def test_candy_wrapper_twist(sample_character):
    """A strong forearm twist collapses the elbow region under LBS (candy wrapper), not under DQS.

    ``left_forearm_twist`` drives ``LeftForeArmRoll``, the joint the ``LeftForeArm`` bone resolves to,
    so vertices shared by the upper-arm and forearm bones are blended across a 2.5 rad twist.
    """
    t = DDCTemplate(sample_character, dtype=torch.float64)
    twist = [d.name for d in sample_character.skeleton.dofs].index("left_forearm_twist")
    x = torch.tensor(sample_character.rest_dofs)[None].clone()
    x[0, twist] += 2.5
    bones = list(sample_character.skin.bones)
    w = sample_character.skin.dense()
    mix = (w[:, bones.index("LeftArm")] > 0.25) & (w[:, bones.index("LeftForeArm")] > 0.25)
    assert mix.sum() > 10

    def cross_section(v):  # minor principal extents of the region
        return torch.linalg.svdvals(v - v.mean(0))[1:].sum()

    r_rest = cross_section(t.rest_verts[mix])
    r_lbs = cross_section(t.pose(x, "lbs")[0][mix])
    r_dqs = cross_section(t.pose(x, "dqs")[0][mix])
    assert r_lbs < 0.7 * r_rest, "LBS loses volume at a strong twist"
    assert r_dqs > 0.95 * r_rest, "DQS keeps the cross-section"
    # and on the untwisted rest of the body both agree exactly
    far = w[:, [bones.index(b) for b in bones if b.startswith("Right")]].sum(1) > 0.99
    assert (t.pose(x, "lbs")[0][far] - t.pose(x, "dqs")[0][far]).abs().max() < 5e-3


def test_dqs_matches_loop_reference():
    """DQS against a per-vertex loop (sign alignment with the first influence, real-norm division)."""
    g = torch.Generator().manual_seed(0)
    Bn, V, K = 5, 12, 3
    axes = torch.nn.functional.normalize(torch.randn(Bn, 3, generator=g, dtype=torch.float64), dim=-1)
    T = torch.eye(4, dtype=torch.float64).repeat(2, Bn, 1, 1)
    T[..., :3, :3] = axis_angle_to_matrix(axes, torch.rand(2, Bn, generator=g, dtype=torch.float64) * 6 - 3)
    T[..., :3, 3] = torch.randn(2, Bn, 3, generator=g, dtype=torch.float64) * 100
    verts = torch.randn(V, 3, generator=g, dtype=torch.float64) * 50
    idx = torch.stack([torch.randperm(Bn, generator=g)[:K] for _ in range(V)])
    w = torch.rand(V, K, generator=g, dtype=torch.float64)
    w = (w / w.sum(1, keepdim=True)).sort(1, descending=True).values
    out = dqs(verts, idx, w, T)
    for b in range(2):
        for v in range(V):
            qs = []
            for k in range(K):
                R = T[b, idx[v, k], :3, :3].numpy()
                tr = T[b, idx[v, k], :3, 3].numpy()
                q = matrix_to_quaternion(torch.tensor(R)).numpy()
                tq = np.array([0, *tr])
                # dual part 0.5 * t * q
                aw, ax, ay, az = tq
                bw, bx, by, bz = q
                d = 0.5 * np.array([aw*bw-ax*bx-ay*by-az*bz, aw*bx+ax*bw+ay*bz-az*by,
                                    aw*by-ax*bz+ay*bw+az*bx, aw*bz+ax*by-ay*bx+az*bw])
                qs.append((q, d))
            r0 = qs[0][0]
            br, bd = np.zeros(4), np.zeros(4)
            for k, (q, d) in enumerate(qs):
                s = -1.0 if np.dot(q, r0) < 0 else 1.0
                br += w[v, k].item() * s * q
                bd += w[v, k].item() * s * d
            n = np.linalg.norm(br)
            br, bd = br / n, bd / n
            R = quaternion_to_matrix(torch.tensor(br)).numpy()
            c = br * np.array([1, -1, -1, -1])
            aw, ax, ay, az = bd
            bw, bx, by, bz = c
            tt = 2 * np.array([aw*bx+ax*bw+ay*bz-az*by, aw*by-ax*bz+ay*bw+az*bx, aw*bz+ax*by-ay*bx+az*bw])
            np.testing.assert_allclose(out[b, v].numpy(), R @ verts[v].numpy() + tt, atol=1e-9)


def test_rigid_skinning_is_exact():
    """One influence per vertex: both skinning methods apply that bone's rigid transform exactly."""
    g = torch.Generator().manual_seed(1)
    T = torch.eye(4, dtype=torch.float64).repeat(1, 2, 1, 1)
    T[0, 1, :3, :3] = axis_angle_to_matrix(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.tensor(0.7, dtype=torch.float64))
    T[0, 1, :3, 3] = torch.tensor([10.0, -5.0, 3.0])
    verts = torch.randn(6, 3, generator=g, dtype=torch.float64)
    idx = torch.tensor([[1, -1]] * 6)
    w = torch.tensor([[1.0, 0.0]] * 6, dtype=torch.float64)
    dense = torch.zeros(6, 2, dtype=torch.float64)
    dense[:, 1] = 1
    expect = verts @ T[0, 1, :3, :3].T + T[0, 1, :3, 3]
    torch.testing.assert_close(dqs(verts, idx, w, T)[0], expect)
    torch.testing.assert_close(lbs(verts, dense, T)[0], expect)


def test_pose_rejects_bad_input(sample_character, unchecked):
    t = DDCTemplate(sample_character)
    with unchecked(), pytest.raises(ValueError, match="dofs: dimension D should be 107"):
        t.pose(torch.zeros(1, 60))
    x = torch.zeros(1, 107)
    x[0, 3] = float("nan")
    with unchecked(), pytest.raises(ValueError, match="non-finite"):
        t.pose(x)
    with unchecked(), pytest.raises(ValueError, match="skinning"):
        DDCTemplate(sample_character, skinning="cubic")


def test_cli_pose_writes_ply(sample_dir, sample_character, sample_motion, tmp_path):
    out = tmp_path / "p.ply"
    r = subprocess.run([sys.executable, "-m", "deliffas", "pose", str(sample_dir / "ddc.character"),
                        str(sample_dir / "skeletoolToGTPose" / "poseAngles.motion"), "--frame", "500",
                        "--skinning", "dqs", "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    import trimesh

    mesh = trimesh.load(out, process=False)
    assert mesh.vertices.shape == (5514, 3) and mesh.faces.shape == (11024, 3)
    np.testing.assert_array_equal(mesh.faces, sample_character.mesh.faces)
    t = DDCTemplate(sample_character, dtype=torch.float64)
    expect = t.pose(torch.tensor(sample_motion.dofs[500:501]))[0].numpy()
    np.testing.assert_allclose(mesh.vertices, expect, atol=1e-3)
    # a missing frame is a clear error, exit code 2
    r = subprocess.run([sys.executable, "-m", "deliffas", "pose", str(sample_dir / "ddc.character"),
                        str(sample_dir / "skeletoolToGTPose" / "poseAngles.motion"), "--frame", "5000",
                        "--out", str(tmp_path / "q.ply")], capture_output=True, text=True)
    assert r.returncode == 2 and "frame 5000 not in motion" in r.stderr
    assert not (tmp_path / "q.ply").exists()
