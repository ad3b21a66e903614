"""fit_body against known answers: a posed procedural body seen by synthetic cameras in a z-up world."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.io.cameras import look_at
from deliffas.geometry.body_fit import BodyFitConfig, fit_body
from deliffas.geometry.smpl_body import procedural_smpl
from deliffas.geometry.templates.smpl import SMPLTemplate

IDS = [1, 2, 4, 5, 7, 8, 10, 11, 15, 16, 17, 18, 19, 20, 21]


@pytest.fixture(scope="module")
def truth():
    template = SMPLTemplate(procedural_smpl(seed=0, target_verts=800), atlas_res=256)
    n = 4
    params = torch.zeros(n, template.num_dofs, dtype=torch.float64)
    params[:, 3] = -np.pi / 2  # root: y-up body in a z-up world
    params[:, 0:3] = torch.tensor([0.2, -0.1, 0.9], dtype=torch.float64)
    t = torch.linspace(0, 1, n, dtype=torch.float64)
    params[:, 3 + 3 * 4] = 0.6 * t  # left knee bends over time
    params[:, 3 + 3 * 19 + 1] = 0.8  # right elbow
    params[:, 3 + 3 * 16 + 2] = -0.9  # left shoulder lowers the arm
    params[:, 75:77] = torch.tensor([1.0, -0.5], dtype=torch.float64)  # betas
    with torch.no_grad():
        verts, joints = template.double().pose_with_joints(params)
    template = template.float()
    cams = [_camera(a) for a in (0, 90, 180, 270)]
    masks = np.stack([_silhouettes(verts[i].numpy(), template.faces.numpy(), cams) for i in range(n)])
    return template, params.numpy(), joints.numpy(), cams, masks


def _camera(azimuth_deg: float):
    from deliffas.io.cameras import Camera

    a = np.deg2rad(azimuth_deg)
    eye = np.array([3000 * np.cos(a), 3000 * np.sin(a), 1200.0])
    K = np.array([[300.0, 0, 80], [0, 300.0, 120], [0, 0, 1]])
    return Camera(f"c{int(azimuth_deg)}", K, look_at(eye, [200, -100, 900], up=[0, 0, 1]), 160, 240)


def _silhouettes(verts, faces, cams):
    from deliffas.data.ingest.write import silhouette  # a filled-triangle raster of the mesh

    return np.stack([silhouette(verts, faces, c) for c in cams])


def _keypoints(joints, rng):
    kp = joints[:, IDS] + rng.normal(0, 10.0, (len(joints), len(IDS), 3))
    conf = np.ones(kp.shape[:2])
    conf[np.arange(len(kp)), rng.integers(0, len(IDS), len(kp))] = 0.0  # one joint missed per frame
    kp[conf == 0] = np.nan
    return kp, conf


def test_keypoints_alone_recover_the_pose_in_a_z_up_world(truth):
    template, params, joints, _, _ = truth
    kp, conf = _keypoints(joints, np.random.default_rng(0))
    res = fit_body(template, kp, conf, IDS, config=BodyFitConfig(iters_keypoints=200))
    assert res.silhouette_iou is None and np.isfinite(res.params).all()
    assert np.allclose(res.params[:, 75:], res.params[:1, 75:])  # one shape
    with torch.no_grad():
        _, fitted = template.double().pose_with_joints(torch.as_tensor(res.params))
    err = np.linalg.norm(fitted.numpy()[:, IDS] - joints[:, IDS], axis=-1)
    assert np.median(err) < 30.0


def test_silhouettes_keep_or_raise_the_overlap(truth):
    template, _, joints, cams, masks = truth
    kp, conf = _keypoints(joints, np.random.default_rng(1))
    cfg = BodyFitConfig(iters_keypoints=150, iters_silhouette=60, mask_height=120)
    with_masks = fit_body(template.float(), kp, conf, IDS, cams, masks, cfg)
    assert with_masks.silhouette_iou.shape == (4, 4)
    assert np.nanmedian(with_masks.silhouette_iou) >= 0.8
    assert np.nanmedian(with_masks.joint_error_mm) < 40.0
