"""SMPL motions <-> smpl template parameter rows and deliffas's per-frame Motion."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.geometry.smpl_params import smpl_to_motion, motion_to_params, params_to_motion, smpl_param_dim
from deliffas.io.body_models.amass import SMPLMotion
from deliffas.io.motion import Motion


def _motion(n: int = 5, pose_dim: int = 156, num_betas: int = 16) -> SMPLMotion:
    rng = np.random.default_rng(0)
    return SMPLMotion(rng.normal(0, 0.3, (n, pose_dim)), rng.normal(0, 1, (n, 3)), rng.normal(0, 1, num_betas), 120.0)


def test_template_rows_and_dynacap_motion():
    m = _motion()
    rows = motion_to_params(m, num_betas=10)
    assert rows.shape == (5, smpl_param_dim(10)) == (5, 85)
    np.testing.assert_array_equal(rows[:, :3], m.trans)
    np.testing.assert_array_equal(rows[:, 3:75], m.smpl_pose)
    np.testing.assert_array_equal(rows[:, 75:], np.tile(m.betas[:10], (5, 1)))
    dm = smpl_to_motion(m, num_betas=10)
    assert isinstance(dm, Motion) and dm.frames.tolist() == [0, 1, 2, 3, 4] and dm.row_of(3) == 3
    np.testing.assert_array_equal(dm.dofs, rows)
    back = params_to_motion(rows, fps=m.fps)
    np.testing.assert_array_equal(back.poses, m.smpl_pose)
    np.testing.assert_array_equal(back.trans, m.trans)
    np.testing.assert_array_equal(back.betas, m.betas[:10])
    assert params_to_motion(motion_to_params(m, num_betas=4)).betas.shape == (10,), "padded to 10"
    with pytest.raises(ValueError, match="num_betas"):
        motion_to_params(m, num_betas=17)
    bad = rows.copy()
    bad[1, 80] += 1
    with pytest.raises(ValueError, match="betas differ"):
        params_to_motion(bad)
