"""fit_smpl on frames generated from known SMPL parameters of the procedural body."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.geometry.smpl_body import procedural_smpl
from deliffas.geometry.smpl_fit import SMPLFitConfig, fit_smpl
from deliffas.geometry.templates import SMPLTemplate

FAST = SMPLFitConfig(adam_steps=0, lbfgs_rounds=12, lbfgs_iters=20)


@pytest.fixture(scope="module")
def template():
    return SMPLTemplate(procedural_smpl(0, target_verts=1500), dtype=torch.float32, atlas_res=256)


@pytest.fixture(scope="module")
def frames(template):
    """(params (6, 85), vertices (6, V, 3) mm, joints (6, 24, 3) mm): shared random betas, moderate poses."""
    rng = np.random.default_rng(7)
    n = 6
    p = np.zeros((n, 85))
    p[:, :3] = rng.normal(0, 0.5, (n, 3))  # metres
    p[:, 3:6] = rng.normal(0, 1.0, (n, 3))  # any global orientation
    p[:, 6:75] = rng.normal(0, 0.3, (n, 69))  # moderate body pose, radians
    p[:, 75:] = rng.normal(0, 1.0, 10)  # one shape for all frames
    params = torch.tensor(p, dtype=torch.float32)
    with torch.no_grad():
        verts, joints = template.pose_with_joints(params)
    return params, verts, joints


def test_fit_to_vertices_within_5mm(template, frames):
    params, verts, _ = frames
    fit = fit_smpl(template, target_verts=verts, config=FAST)
    assert fit.params.shape == params.shape and fit.params.dtype == verts.dtype and fit.betas.shape == (10,)
    with torch.no_grad():
        err = (template.pose(fit.params) - verts).norm(dim=-1).mean(1)  # (N,) mm
    torch.testing.assert_close(err, fit.residual_mm)
    assert float(err.max()) <= 5.0, f"mean vertex error per frame {err.tolist()} mm"
    assert torch.equal(fit.params[:, 75:], fit.betas.expand(len(params), 10)), "one shape for all frames"


def test_fit_to_joints(template, frames):
    params, verts, joints = frames
    fit = fit_smpl(template, target_joints=joints, config=FAST)
    assert float(fit.residual_mm.max()) <= 5.0, f"mean joint error per frame {fit.residual_mm.tolist()} mm"


def test_bad_inputs(template, frames):
    _, verts, joints = frames
    with pytest.raises(ValueError, match="target_verts .* and/or target_joints"):
        fit_smpl(template)
    with pytest.raises(ValueError, match="target_verts: dimension V"):
        fit_smpl(template, target_verts=verts[:, :10])
    with pytest.raises(ValueError, match="target_joints: dimension J"):
        fit_smpl(template, target_joints=joints[:, :20])
    bad = verts.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="target_verts: 1 non-finite"):
        fit_smpl(template, target_verts=bad)
    with pytest.raises(ValueError, match="template is torch.float32 .* targets are torch.float64"):
        fit_smpl(template, target_verts=verts.double())


def test_surface_fit_recovers_a_translated_copy(tmp_path):
    """fit_smpl_to_surfaces (no correspondences): a translated copy of the rest body is matched within 5 mm."""
    import torch

    from deliffas.geometry.smpl_body import make_procedural_smpl
    from deliffas.geometry.smpl_surface_fit import SurfaceFitConfig, fit_smpl_to_surfaces
    from deliffas.geometry.templates import SMPLTemplate

    smpl = SMPLTemplate(make_procedural_smpl(tmp_path, target_verts=800), dtype=torch.float32)
    with torch.no_grad():
        target = smpl.pose(smpl.rest_params()).numpy()[0] + [30.0, -20.0, 10.0]
    fit = fit_smpl_to_surfaces(smpl, [target, target + [5.0, 0, 0]], SurfaceFitConfig(first_iters=80, frame_iters=20))
    assert fit.params.shape == (2, smpl.num_dofs) and fit.residual_mm.max() < 5.0
    assert np.allclose(fit.params[0, :3] * 1000, [30.0, -20.0, 10.0], atol=5.0)
