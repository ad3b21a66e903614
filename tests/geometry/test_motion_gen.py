"""Procedural motions: smooth, deterministic, within limits, the same joint motion on any DDC-named skeleton."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.geometry.motion_gen import MAX_YAW_RATE, known_dof_names, procedural_motion
from deliffas.geometry.procedural import procedural_skeleton

STYLES = ("walk_in_place", "dance", "mixed")


@pytest.fixture(scope="module")
def proc():
    return procedural_skeleton()


@pytest.mark.parametrize("style", STYLES)
def test_smooth_in_joint_units(proc, style):
    skel, rest = proc
    m = procedural_motion(skel, 300, seed=4, style=style, rest_dofs=rest)
    assert m.dofs.shape == (300, skel.num_dofs) and np.isfinite(m.dofs).all()
    np.testing.assert_array_equal(m.frames, np.arange(300))
    p = m.dofs @ skel.dof_weights()  # joint parameters: rad, or mm for Root_t*
    revolute = np.array([j.type == "revolute" for j in skel.joints])
    d1 = np.abs(np.diff(p, axis=0))
    d2 = np.abs(np.diff(p, n=2, axis=0))
    assert d1[:, revolute].max() < 0.2, "at most ~11 degrees per frame at 25 fps"
    assert d1[:, ~revolute].max() < 15.0, "root moves less than 15 mm per frame"
    assert d2[:, revolute].max() < 0.05, "no jerks"
    assert d1[:, revolute].max() > 1e-3, "it does move"


def test_deterministic_and_seeded(proc):
    skel, rest = proc
    a = procedural_motion(skel, 50, seed=7, style="mixed", rest_dofs=rest)
    b = procedural_motion(skel, 50, seed=7, style="mixed", rest_dofs=rest)
    c = procedural_motion(skel, 50, seed=8, style="mixed", rest_dofs=rest)
    np.testing.assert_array_equal(a.dofs, b.dofs)
    assert np.abs(a.dofs - c.dofs).max() > 0.05


def test_walk_alternates_legs_and_turns_slowly(proc):
    skel, rest = proc
    names = [d.name for d in skel.dofs]
    m = procedural_motion(skel, 500, seed=0, style="walk_in_place", rest_dofs=rest)
    lh, rh = m.dofs[:, names.index("left_hip_x")], m.dofs[:, names.index("right_hip_x")]
    assert np.corrcoef(lh, rh)[0, 1] < -0.9, "legs in antiphase"
    la = m.dofs[:, names.index("left_shoulder_y")]
    assert np.corrcoef(lh, la)[0, 1] < -0.9, "arm swings back when the same-side leg swings forward"
    knee = m.dofs[:, names.index("left_knee")]
    assert knee.max() <= rest[names.index("left_knee")] + 1e-12 and knee.min() < -0.5, "knees only flex"
    yaw = m.dofs[:, names.index("rotate_y")] * 3.0  # Root_ry weight 3
    assert (np.diff(yaw) > 0).all() and np.diff(yaw).max() <= MAX_YAW_RATE + 1e-12
    assert yaw[-1] - yaw[0] == pytest.approx(2 * np.pi, rel=1e-6), "a full turn over 500 frames: every side seen"
    t = m.dofs[:, :3] * 1000.0
    assert np.abs(t - t[0]).max() < 60, "in place: the root moves a little"


def test_short_sequence_caps_yaw_rate(proc):
    skel, rest = proc
    m = procedural_motion(skel, 10, seed=0, rest_dofs=rest)
    yaw = m.dofs[:, [d.name for d in skel.dofs].index("rotate_y")] * 3.0
    assert np.diff(yaw).max() == pytest.approx(MAX_YAW_RATE)


def test_limits_respected(proc):
    skel, rest = proc
    m = procedural_motion(skel, 400, seed=1, style="dance", rest_dofs=rest)
    for d, dof in enumerate(skel.dofs):
        if dof.limits is not None:
            lo, hi = dof.limits
            assert m.dofs[:, d].min() >= min(lo, rest[d]) - 1e-12 and m.dofs[:, d].max() <= max(hi, rest[d]) + 1e-12


def test_bad_arguments(proc, unchecked):
    skel, rest = proc
    with unchecked(), pytest.raises(ValueError, match="style"):
        procedural_motion(skel, 5, style="jog")
    with unchecked(), pytest.raises(ValueError, match="rest_dofs"):
        procedural_motion(skel, 5, rest_dofs=np.zeros(3))
    with unchecked(), pytest.raises(ValueError, match="num_frames"):
        procedural_motion(skel, 0)


def test_ddc_skeleton_same_joint_motion(sample_character, proc):
    """One generator drives both: unknown DOFs stay at rest, shared DOFs get the same joint motion."""
    ddc = sample_character
    skel, rest = proc
    md = procedural_motion(ddc.skeleton, 120, seed=3, style="mixed", rest_dofs=ddc.rest_dofs)
    mp = procedural_motion(skel, 120, seed=3, style="mixed", rest_dofs=rest)
    known = known_dof_names()
    ddc_names = [d.name for d in ddc.skeleton.dofs]
    for d, dof in enumerate(ddc.skeleton.dofs):
        if dof.name not in known:
            np.testing.assert_array_equal(md.dofs[:, d], ddc.rest_dofs[d], err_msg=dof.name)
    for name in ("left_knee", "right_shoulder_y", "spine_twist", "left_ankle_x", "rotate_y"):
        i, j = ddc_names.index(name), [d.name for d in skel.dofs].index(name)
        gain_d = sum(abs(w) for _, w in ddc.skeleton.dofs[i].joints)
        gain_p = sum(abs(w) for _, w in skel.dofs[j].joints)
        off_d = (md.dofs[:, i] - ddc.rest_dofs[i]) * gain_d
        off_p = (mp.dofs[:, j] - rest[j]) * gain_p
        lim = ddc.skeleton.dofs[i].limits
        unclipped = np.ones(120, bool) if lim is None else (md.dofs[:, i] > lim[0]) & (md.dofs[:, i] < lim[1])
        np.testing.assert_allclose(off_d[unclipped], off_p[unclipped], atol=1e-9, err_msg=name)
    from deliffas.geometry.templates import DDCTemplate

    v = DDCTemplate(ddc).pose(torch.tensor(md.dofs[::20], dtype=torch.float32))
    assert torch.isfinite(v).all()
    height = (v[..., 1].max(dim=1).values - v[..., 1].min(dim=1).values)
    assert (height > 1400).all() and (height < 1900).all(), "still a standing person"
