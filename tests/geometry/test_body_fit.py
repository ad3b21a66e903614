"""fit_body on a synthetic capture: the procedural body posed in a z-up world, noisy keypoints with gaps, 4 cameras
and the true body's silhouettes as masks."""

from __future__ import annotations

import copy
import dataclasses

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from deliffas.geometry import body_fit_silhouette as sil
from deliffas.geometry.body_fit import BodyFitConfig, fit_body, initial_body_params
from deliffas.geometry.body_fit_offsets import with_rest_offsets
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.smpl_body import procedural_smpl
from deliffas.geometry.templates import SMPLTemplate
from deliffas.io.cameras import Camera, look_at

IDS = (1, 2, 4, 5, 7, 8, 10, 11, 15, 16, 17, 18, 19, 20, 21)
"""hips, knees, ankles, feet, head, shoulders, elbows, wrists (the ingest detector's 15)."""
N, NB = 6, 10
FAST = BodyFitConfig(iters_keypoints=200, iters_silhouette=80, mask_height=128, mask_samples=128)
FULL = (1080, 1920)
"""The cameras' image (H, W); the masks are given at a quarter of it (same aspect)."""


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """One torch thread from the module's first fixture on (conftest's per-test fixture comes after the module's
    fixtures: a pool started with more threads and then cut to one ran this module's fits ~10x slower)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def template():
    return SMPLTemplate(procedural_smpl(0, target_verts=800), atlas_res=64)


def _true_params() -> np.ndarray:
    """(N, 85) a smooth motion in a z-up world: turning, bent knees and elbows, arms down, a non-mean shape."""
    t = np.arange(N) / 15.0
    p = np.zeros((N, 75 + NB))
    up_z = Rotation.from_euler("x", np.pi / 2)  # the body's y (up) -> world z
    p[:, 3:6] = (Rotation.from_euler("z", (0.3 + 0.6 * np.sin(2 * np.pi * t))[:, None]) * up_z).as_rotvec()
    p[:, :3] = np.stack([0.3 + 0.2 * t, -0.1 + 0.1 * t, np.full(N, 0.95)], axis=1)  # metres

    def dof(joint: int, axis: int) -> int:
        return 3 + 3 * joint + axis

    wave = np.sin(2 * np.pi * t)
    p[:, dof(1, 0)], p[:, dof(2, 0)] = -0.4 - 0.2 * wave, -0.2 + 0.2 * wave  # hips flexed
    p[:, dof(4, 0)], p[:, dof(5, 0)] = 0.6 + 0.3 * wave, 0.3 + 0.2 * wave  # knees bent
    p[:, dof(16, 2)], p[:, dof(17, 2)] = -1.1 + 0.2 * wave, 1.1 - 0.2 * wave  # arms down
    p[:, dof(18, 1)], p[:, dof(19, 1)] = -0.9 - 0.3 * wave, 0.7 + 0.3 * wave  # elbows bent
    p[:, dof(3, 0)] = 0.15  # leaning forwards
    p[:, 75:] = [1.0, 1.5, -0.5, 0.5, 1.0, -1.0, 0.3, 0.5, 0.5, -0.5]
    return p


def _cameras() -> list[Camera]:
    centre = np.array([300.0, -100.0, 950.0])
    K = np.array([[1400.0, 0.0, FULL[1] / 2], [0.0, 1400.0, FULL[0] / 2], [0.0, 0.0, 1.0]])
    cams = []
    for c in range(4):
        a = np.pi / 2 * c + 0.3
        eye = centre + [3200.0 * np.cos(a), 3200.0 * np.sin(a), 300.0 * (c % 2)]
        cams.append(Camera(f"c{c}", K, look_at(eye, centre, up=(0.0, 0.0, 1.0)), FULL[1], FULL[0]))
    return cams


def _masks(verts: np.ndarray, faces: np.ndarray, cams: list[Camera], h: int, w: int) -> np.ndarray:
    """(N, C, h, w) bool: the meshes' filled triangles at 2x, kept where at least half of a pixel is covered."""
    out = np.zeros((len(verts), len(cams), h, w), bool)
    for c, cam in enumerate(cams):
        K = cam.rescaled(2 * w, 2 * h).K
        for n, v in enumerate(verts):
            x = (v @ cam.R.T + cam.t) @ K.T
            fixed = np.round((x[:, :2] / x[:, 2:] - 0.5) * 16).astype(np.int32)
            image = np.zeros((2 * h, 2 * w), np.uint8)
            for tri in fixed[faces]:
                cv2.fillConvexPoly(image, tri, 255, cv2.LINE_8, 4)
            out[n, c] = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA) >= 128
    return out


@pytest.fixture(scope="module")
def scene(template):
    """Truth and observations: keypoints with 10 mm noise and one missing joint per frame, masks at 270x480."""
    rng = np.random.default_rng(3)
    params = _true_params()
    with torch.no_grad():
        verts, joints = template.pose_with_joints(torch.as_tensor(params, dtype=torch.float32))
    verts, joints = verts.double().numpy(), joints.double().numpy()
    keypoints = joints[:, IDS] + rng.normal(0.0, 10.0, (N, len(IDS), 3))
    conf = rng.uniform(0.6, 1.0, (N, len(IDS)))
    missing = rng.integers(0, len(IDS), N)
    conf[np.arange(N), missing] = 0.0
    keypoints[np.arange(N), missing] = np.nan
    cams = _cameras()
    masks = _masks(verts, template.faces.numpy(), cams, FULL[0] // 4, FULL[1] // 4)
    return dict(params=params, joints=joints[:, IDS], keypoints=keypoints, conf=conf, cameras=cams, masks=masks)


@pytest.fixture(scope="module")
def keypoint_fit(template, scene):
    """The keypoint stage only, its silhouettes scored against the masks (``iters_silhouette`` = 0)."""
    config = dataclasses.replace(FAST, iters_silhouette=0)
    return fit_body(template, scene["keypoints"], scene["conf"], IDS, scene["cameras"], scene["masks"], config)


@pytest.fixture(scope="module")
def silhouette_fit(template, scene):
    return fit_body(template, scene["keypoints"], scene["conf"], IDS, scene["cameras"], scene["masks"], FAST)


def _joint_error(template, params: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(N, J) mm between the fitted joints IDS and the noise-free true ones."""
    with torch.no_grad():
        joints = template.pose_with_joints(torch.as_tensor(params, dtype=torch.float32))[1].double().numpy()
    return np.linalg.norm(joints[:, IDS] - truth, axis=2)


def test_initialisation_finds_a_z_up_body(template, scene):
    start = initial_body_params(template, scene["keypoints"], scene["conf"], IDS)
    assert start.shape == (N, 75 + NB) and start.dtype == np.float64 and np.isfinite(start).all()
    fitted, true = Rotation.from_rotvec(start[:, 3:6]), Rotation.from_rotvec(scene["params"][:, 3:6])
    up = fitted.apply([0.0, 1.0, 0.0])
    assert (up[:, 2] > np.cos(np.radians(15))).all(), f"the body's up in the world: {up.round(2)}"
    angle = np.degrees((fitted.inv() * true).magnitude())
    assert angle.max() < 15, f"initial root orientation off by {angle.round(1)} degrees"
    err = _joint_error(template, start, scene["joints"])
    assert np.median(err) < 80, f"initial joints {np.median(err):.0f} mm from the truth (median)"
    zero = fit_body(template, scene["keypoints"], scene["conf"], IDS,
                    config=dataclasses.replace(FAST, iters_keypoints=0))
    np.testing.assert_allclose(zero.params, start, atol=1e-6)


def test_keypoint_only_fit(template, scene):
    fit = fit_body(template, scene["keypoints"], scene["conf"], IDS, config=FAST)
    assert fit.silhouette_iou is None
    assert fit.params.shape == (N, 75 + NB) and fit.params.dtype == np.float64 and np.isfinite(fit.params).all()
    assert (fit.params[:, 75:] == fit.params[0, 75:]).all(), "one shape for all frames"
    invalid = scene["conf"] == 0
    assert fit.joint_error_mm.shape == (N, len(IDS))
    assert np.isnan(fit.joint_error_mm[invalid]).all() and np.isfinite(fit.joint_error_mm[~invalid]).all()
    err = _joint_error(template, fit.params, scene["joints"])
    assert np.median(err) < 25 and err.max() < 80, f"joints {np.median(err):.1f} mm (median), {err.max():.0f} max"
    assert {"keypoints", "pose_prior", "shape_prior", "smooth", "total"} <= set(fit.losses)
    assert all(np.isfinite(v) for v in fit.losses.values())


def test_silhouette_fit_covers_the_masks(template, scene, keypoint_fit, silhouette_fit):
    fit = silhouette_fit
    assert fit.silhouette_iou.shape == (N, 4) and np.isfinite(fit.params).all()
    assert (fit.params[:, 75:] == fit.params[0, 75:]).all(), "one shape for all frames"
    iou, before = np.median(fit.silhouette_iou), np.median(keypoint_fit.silhouette_iou)
    assert iou >= 0.85, f"silhouette IoU {iou:.3f} (median)"
    assert iou >= before - 0.005, f"the silhouette stage lowered the IoU: {before:.3f} -> {iou:.3f}"
    err = _joint_error(template, fit.params, scene["joints"])
    assert np.median(err) < 30, f"joints {np.median(err):.1f} mm from the truth (median)"
    # the body covers the mask (DELIFFAS's shell lies outside the template): few mask pixels left out
    # the fitted body is the template with the rest offsets in its v_template
    fitted = copy.deepcopy(template)
    fitted.v_template += torch.as_tensor(fit.rest_offsets_mm, dtype=fitted.v_template.dtype)
    targets = sil.prepare_silhouettes(scene["masks"], scene["cameras"], FAST.mask_height, 1, 0, torch.zeros(1))
    with torch.no_grad():
        uv, depth = sil.project(fitted.pose(torch.as_tensor(fit.params, dtype=torch.float32)), targets.proj)
    drawn = sil.rasterize_silhouettes(uv.double().numpy(), depth.double().numpy(), template.faces.numpy(),
                                      targets.masks.shape[2:])
    np.testing.assert_allclose(sil.silhouette_iou(drawn, targets.masks), fit.silhouette_iou)
    covered = (drawn & targets.masks).sum(axis=(2, 3)) / targets.masks.sum(axis=(2, 3))
    assert np.median(covered) >= 0.95, f"the body covers {np.median(covered):.3f} of the masks (median)"


def test_frames_without_torso_keypoints(template, scene):
    """A frame with no hip or shoulder keypoint takes its neighbours' root; nothing becomes NaN."""
    keypoints, conf = scene["keypoints"].copy(), scene["conf"].copy()
    torso = [IDS.index(j) for j in (1, 2, 16, 17)]
    keypoints[2][torso], conf[2][torso] = np.nan, 0.0
    conf[4] = 0.0  # and a frame with no keypoint at all
    keypoints[4] = np.nan
    fit = fit_body(template, keypoints, conf, IDS, config=dataclasses.replace(FAST, iters_keypoints=100))
    assert np.isfinite(fit.params).all() and np.isnan(fit.joint_error_mm[4]).all()
    err = _joint_error(template, fit.params, scene["joints"])
    assert err[[2, 4]].max() < 120, f"frames 2 and 4: {err[[2, 4]].max(axis=1).round(0)} mm (max)"


def test_bad_inputs(template, scene):
    kp, conf, cams, masks = scene["keypoints"], scene["conf"], scene["cameras"], scene["masks"]
    with pytest.raises(ValueError, match="landmarks: expected"):
        fit_body(template, kp, conf, IDS[:-1] + (24,))
    with pytest.raises(ValueError, match="no valid keypoint"):
        fit_body(template, kp, np.zeros_like(conf), IDS)
    with pytest.raises(ValueError, match="masks need their cameras"):
        fit_body(template, kp, conf, IDS, masks=masks)
    with pytest.raises(ValueError, match="masks: dimension C"):
        fit_body(template, kp, conf, IDS, cams[:3], masks)
    with pytest.raises(ValueError, match="aspect"):
        fit_body(template, kp, conf, IDS, cams, np.ascontiguousarray(masks[:, :, :, :200]))


@pytest.fixture(scope="module")
def clothed(template, scene):
    """The scene's body with a 'belly bag': the front of its torso pushed out by up to 50 mm along the rest normals
    (smooth), and its masks; the shape space cannot make it."""
    rest = template.v_template.double().numpy()
    normals = vertex_normals(rest, template.faces.numpy())
    height = (rest[:, 1] - rest[:, 1].min()) / np.ptp(rest[:, 1])
    torso = (np.clip(1.0 - np.abs(height - 0.58) / 0.12, 0.0, 1.0) * (np.abs(rest[:, 0]) < 150.0)
             * np.clip(normals[:, 2], 0.0, 1.0))  # the body faces +z at rest
    offsets = 50.0 * torso[:, None] * normals
    body = copy.deepcopy(template)
    body.v_template += torch.as_tensor(offsets, dtype=body.v_template.dtype)
    with torch.no_grad():
        verts = body.pose(torch.as_tensor(scene["params"], dtype=torch.float32)).double().numpy()
    masks = _masks(verts, template.faces.numpy(), scene["cameras"], FULL[0] // 4, FULL[1] // 4)
    return dict(torso=torso > 0.3, masks=masks)


def test_rest_offsets_follow_what_the_shape_space_cannot(template, scene, clothed):
    """With offsets the fit pushes the bag's vertices out (more than the others), without losing IoU; the offsets in
    a model file's v_template reproduce the fitted body."""
    fits = {on: fit_body(template, scene["keypoints"], scene["conf"], IDS, scene["cameras"], clothed["masks"],
                         dataclasses.replace(FAST, offsets=on)) for on in (False, True)}
    assert not fits[False].rest_offsets_mm.any()
    iou = {on: np.median(f.silhouette_iou) for on, f in fits.items()}
    assert iou[True] >= iou[False] - 0.01, f"IoU with offsets {iou[True]:.3f}, without {iou[False]:.3f}"
    normals = vertex_normals(template.v_template.double().numpy(), template.faces.numpy())
    along = (fits[True].rest_offsets_mm * normals).sum(1)
    bag, others = np.median(along[clothed["torso"]]), np.median(np.abs(along[~clothed["torso"]]))
    assert bag > 3.0 and bag > 2.0 * others, f"offsets: {bag:.1f} mm on the bag, {others:.1f} mm elsewhere (median)"
    assert np.abs(along).max() < 40.0
    data = procedural_smpl(0, target_verts=800)
    fitted = SMPLTemplate(with_rest_offsets(data, fits[True].rest_offsets_mm), atlas_res=64)
    params = torch.as_tensor(fits[True].params[:2], dtype=torch.float32)
    with torch.no_grad():
        direct = copy.deepcopy(template)
        direct.v_template += torch.as_tensor(fits[True].rest_offsets_mm, dtype=direct.v_template.dtype)
        np.testing.assert_allclose(fitted.pose(params).numpy(), direct.pose(params).numpy(), atol=1e-3)
    with pytest.raises(ValueError, match="rest offsets"):
        with_rest_offsets(data, np.zeros((3, 3)))
