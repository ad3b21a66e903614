"""Body landmarks: joints equal the posed joints; surface points sit where the docstring says and follow the body."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.data.ingest.detect import BODY_LANDMARK_NAMES
from deliffas.geometry.body_fit import BodyFitConfig, fit_body
from deliffas.geometry.body_landmarks import (LANDMARK_NAMES, SURFACE_LANDMARKS, body_landmarks,
                                              posed_template_landmarks)
from deliffas.geometry.smpl_body import SMPL_JOINT_NAMES, procedural_smpl
from deliffas.geometry.templates.smpl import SMPLTemplate


@pytest.fixture(scope="module")
def template():
    return SMPLTemplate(procedural_smpl(seed=0, target_verts=800), atlas_res=256, dtype=torch.float64)


def _landmarks(template, names):
    return body_landmarks(template.v_template, template.J_regressor, template.lbs_weights, names)


def _params(template, n=3, seed=0):
    rng = np.random.default_rng(seed)
    params = torch.zeros(n, template.num_dofs, dtype=torch.float64)
    params[:, 3:75] = torch.as_tensor(rng.normal(0, 0.3, (n, 72)))
    params[:, :3] = torch.as_tensor(rng.normal(0, 0.2, (n, 3)))
    params[:, 75:] = torch.as_tensor(rng.normal(0, 1.0, (n, template.num_betas)))
    return params


def test_joint_landmarks_are_the_posed_joints(template):
    params = _params(template)
    lm = _landmarks(template, SMPL_JOINT_NAMES)
    with torch.no_grad():
        _, joints = template.pose_with_joints(params)
        points = posed_template_landmarks(template, lm, params)
    assert np.allclose(points.numpy(), joints.numpy(), atol=1e-6)
    assert lm.joints.tolist() == list(range(24)) and lm.bones.tolist() == list(range(24))


def test_surface_landmarks_lie_where_they_are_defined(template):
    lm = _landmarks(template, tuple(SURFACE_LANDMARKS))
    rest = posed_template_landmarks(template, lm, template.rest_params(1).double())[0].numpy()
    at = dict(zip(lm.names, rest))
    joints = (template.J_regressor @ template.v_template).numpy()
    head, l_ankle, r_ankle = joints[15], joints[7], joints[8]
    assert at["l_ear"][0] > head[0] + 40 and at["r_ear"][0] < head[0] - 40  # either side of the head
    assert at["nose"][2] > head[2] + 40  # in front
    for side, ankle in (("l", l_ankle), ("r", r_ankle)):
        assert at[f"{side}_toe"][2] > ankle[2] + 80 and at[f"{side}_toe"][1] < ankle[1]
        assert at[f"{side}_heel"][2] < ankle[2] and at[f"{side}_heel"][1] < ankle[1]
    assert (lm.joints == -1).all() and np.allclose(lm.weights.sum(1), 1.0)


def test_surface_landmarks_follow_the_posed_surface(template):
    """Carried rigidly by one bone, a surface landmark stays within a few mm of its vertices as skinned."""
    params = _params(template, seed=1)
    lm = _landmarks(template, tuple(SURFACE_LANDMARKS))
    with torch.no_grad():
        verts = template.pose(params).numpy()
        points = posed_template_landmarks(template, lm, params).numpy()
    gap = np.linalg.norm(points - np.einsum("jv,nvk->njk", lm.weights, verts), axis=-1)
    assert np.median(gap) < 8.0 and gap.max() < 40.0  # the heels blend ankle and foot the most


def test_unknown_names_are_refused_with_the_list(template):
    with pytest.raises(ValueError, match="unknown; expected names of"):
        _landmarks(template, ["l_ear", "left_pinky"])
    assert set(BODY_LANDMARK_NAMES) <= set(LANDMARK_NAMES)


def test_fit_recovers_the_ingest_landmarks(template):
    """Keypoints at the true landmarks of the ingest (ears, nose, toes, heels among them) give back the body."""
    truth = _params(template, n=4, seed=2)
    truth[:, 3:75] *= 0.5
    lm = _landmarks(template, BODY_LANDMARK_NAMES)
    with torch.no_grad():
        target = posed_template_landmarks(template, lm, truth).numpy()
        true_verts = template.pose(truth).numpy()
    rng = np.random.default_rng(0)
    kp = target + rng.normal(0, 5.0, target.shape)
    res = fit_body(template.float(), kp, np.ones(kp.shape[:2]), lm, config=BodyFitConfig(iters_keypoints=300),
                   frame_ids=np.arange(4) * 10)  # unrelated poses: no smoothness between them
    assert np.nanmedian(res.joint_error_mm) < 15.0
    with torch.no_grad():
        fitted = template.pose(torch.as_tensor(res.params)).numpy()
    assert np.median(np.linalg.norm(fitted - true_verts, axis=-1)) < 40.0
