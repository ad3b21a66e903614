"""Robust multi-view triangulation: exact and noisy rings of cameras, outlier views, missing and low-confidence
detections, points behind a camera, the result's shapes and the JSON summary."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from deliffas.geometry import triangulate as tri_mod
from deliffas.geometry.triangulate import Triangulation, reprojection_summary, triangulate
from deliffas.io.cameras import Camera, look_at

TARGET = np.array([0.0, 1000.0, 0.0])  # world y-up, mm: a standing person's middle


def ring(num: int, radius: float = 3000.0, width: int = 1280, height: int = 960) -> list[Camera]:
    """``num`` cameras on a circle around TARGET, at slightly varying heights, all looking at it."""
    K = np.array([[1100.0, 0, width / 2], [0, 1050.0, height / 2], [0, 0, 1]])
    cams = []
    for i in range(num):
        a = 2 * np.pi * i / num + 0.1
        eye = TARGET + [radius * np.cos(a), 300.0 * np.sin(3 * a), radius * np.sin(a)]
        cams.append(Camera(f"cam{i}", K.copy(), look_at(eye, TARGET), width, height))
    return cams


def random_points(n: int, j: int, seed: int = 0) -> np.ndarray:
    """(N, J, 3) world mm within a 1.2 m box around TARGET."""
    return TARGET + np.random.default_rng(seed).uniform(-600, 600, size=(n, j, 3))


def project(cams: list[Camera], X: np.ndarray) -> np.ndarray:
    """(C, N, J, 2) exact pixel projections of (N, J, 3) points."""
    return np.stack([cam.project(X.reshape(-1, 3))[0].reshape(*X.shape[:2], 2) for cam in cams])


def full_conf(C: int, X: np.ndarray, value: float = 0.9) -> np.ndarray:
    return np.full((C, *X.shape[:2]), value)


@pytest.mark.parametrize("num_cams", [4, 8])
def test_exact_projections_recovered(num_cams):
    cams = ring(num_cams)
    X = random_points(20, 5, seed=num_cams)
    t = triangulate(project(cams, X), full_conf(num_cams, X), cams)
    assert t.valid.all() and t.used.all()
    np.testing.assert_allclose(t.points, X, atol=1e-6, rtol=0)
    assert np.nanmax(t.reprojection_px) < 1e-6


def test_result_shapes_and_dtypes_float32_input():
    cams = ring(5)
    X = random_points(7, 3)
    t = triangulate(project(cams, X).astype(np.float32), full_conf(5, X).astype(np.float32), cams)
    assert isinstance(t, Triangulation)
    assert t.points.shape == (7, 3, 3) and t.points.dtype == np.float64
    assert t.valid.shape == (7, 3) and t.valid.dtype == bool
    assert t.used.shape == (7, 3, 5) and t.used.dtype == bool
    assert t.reprojection_px.shape == (7, 3, 5) and t.reprojection_px.dtype == np.float64
    np.testing.assert_allclose(t.points, X, atol=0.5)  # float32 pixels: ~1e-4 px rounding


def test_pixel_noise_small_error_and_sensible_stats():
    cams = ring(6)
    X = random_points(50, 8, seed=1)
    rng = np.random.default_rng(2)
    x = project(cams, X) + rng.normal(0.0, 1.0, size=(6, 50, 8, 2))
    t = triangulate(x, rng.uniform(0.5, 1.0, size=(6, 50, 8)), cams)
    assert t.valid.all() and t.used.all()  # 1 px noise: no view beyond 15 px
    dist = np.linalg.norm(t.points - X, axis=-1)
    assert np.median(dist) < 3.0 and dist.max() < 10.0  # 1 px ~ 2.7 mm at 3 m, six views
    # the reprojection residual of a 1-px-noise point: the 2-D error less the 3 fitted dofs, about 1 px
    assert 0.5 < np.median(t.reprojection_px) < 1.5 and t.reprojection_px.max() < 6.0
    s = reprojection_summary(t, [f"j{k}" for k in range(8)], [c.name for c in cams])
    assert 0.5 < s["median_px"] < 1.5 and s["median_px"] < s["p90_px"] < 3.0
    assert s["triangulated_fraction"] == 1.0
    assert all(v["rejected_fraction"] == 0.0 and v["detections"] == 400 for v in s["per_camera"].values())


def test_noisy_points_match_the_weighted_least_squares_optimum():
    least_squares = pytest.importorskip("scipy.optimize").least_squares
    cams = ring(5)
    X = random_points(4, 3, seed=12)
    rng = np.random.default_rng(13)
    x = project(cams, X) + rng.normal(0.0, 2.0, size=(5, 4, 3, 2))
    conf = rng.uniform(0.4, 1.0, size=(5, 4, 3))
    t = triangulate(x, conf, cams)
    for n, j in np.ndindex(4, 3):
        def residuals(p, n=n, j=j):
            return np.concatenate([(cam.project(p[None])[0][0] - x[k, n, j]) * conf[k, n, j]
                                   for k, cam in enumerate(cams)])

        best = least_squares(residuals, t.points[n, j], xtol=1e-12).x
        assert np.linalg.norm(best - t.points[n, j]) < 0.05  # mm; the DLT's distance to the optimum


@pytest.mark.parametrize("kind", ["offset", "other_person", "swap"])
@pytest.mark.parametrize("num_cams", [3, 4, 7])
def test_one_wrong_view_rejected_and_point_recovered(kind, num_cams):
    cams = ring(num_cams)
    X = random_points(30, 4, seed=3)
    x = project(cams, X)
    bad = num_cams - 1
    if kind == "offset":
        x[bad] += [120.0, -80.0]
    elif kind == "other_person":
        x[bad] = project(cams, X + [700.0, 0.0, 500.0])[bad]
    else:  # left/right swap of joints 0 <-> 1 and 2 <-> 3 in one view
        x[bad] = x[bad][:, [1, 0, 3, 2]]
    t = triangulate(x, full_conf(num_cams, X), cams)
    # (N, J) the view is clearly wrong: a detection ~30 px off can pass as three views each within 15 px
    far = np.linalg.norm(x[bad] - project(cams, X)[bad], axis=-1) > 60.0
    assert far.sum() > 0.7 * far.size
    assert t.valid.all()
    assert (np.where(t.used, t.reprojection_px, 0.0) <= 15.0).all()  # the others: consistent within 15 px
    np.testing.assert_allclose(t.points[far], X[far], atol=1e-6, rtol=0)
    assert not t.used[..., bad][far].any()
    assert t.used[..., :bad].all()
    assert (t.reprojection_px[..., bad][far] > 15.0).all()  # reported for the rejected view too
    s = reprojection_summary(t, list("abcd"), [c.name for c in cams])
    rejected = s["per_camera"][cams[bad].name]["rejected_fraction"]
    assert rejected == pytest.approx(1.0 - t.used[..., bad].mean()) and rejected >= far.mean()
    assert s["per_camera"][cams[0].name]["rejected_fraction"] == 0.0


def test_weight_favours_confident_views_but_high_weight_outlier_still_rejected():
    cams = ring(5)
    X = random_points(10, 2, seed=4)
    x = project(cams, X)
    x[0] += 40.0
    conf = full_conf(5, X, 0.4)
    conf[0] = 1.0  # the wrong view is the most confident
    t = triangulate(x, conf, cams)
    assert t.valid.all() and not t.used[..., 0].any() and t.used[..., 1:].all()
    np.testing.assert_allclose(t.points, X, atol=1e-6, rtol=0)


def test_single_detection_and_low_confidence_are_invalid():
    cams = ring(4)
    X = random_points(6, 3, seed=5)
    conf = full_conf(4, X)
    conf[1:, 0, 0] = 0.0  # point (0, 0): one view only
    conf[:, 1, 1] = 0.29  # point (1, 1): all below min_conf
    conf[:, 2, 2] = np.nan  # point (2, 2): NaN confidences are misses
    t = triangulate(project(cams, X), conf, cams)
    for n, j in [(0, 0), (1, 1), (2, 2)]:
        assert not t.valid[n, j] and np.isnan(t.points[n, j]).all()
        assert not t.used[n, j].any() and np.isnan(t.reprojection_px[n, j]).all()
    others = np.ones((6, 3), bool)
    others[[0, 1, 2], [0, 1, 2]] = False
    assert t.valid[others].all()
    np.testing.assert_allclose(t.points[others], X[others], atol=1e-6, rtol=0)


def test_missed_views_and_garbage_below_threshold_ignored():
    cams = ring(6)
    X = random_points(8, 4, seed=6)
    x = project(cams, X)
    conf = full_conf(6, X)
    conf[2] = 0.1
    x[2] = 1e9  # a low-confidence view's pixel is never read
    x[4, 0, 0] = np.nan  # a non-finite pixel is a miss whatever its confidence
    t = triangulate(x, conf, cams)
    assert t.valid.all()
    np.testing.assert_allclose(t.points, X, atol=1e-6, rtol=0)
    assert not t.used[..., 2].any() and np.isnan(t.reprojection_px[..., 2]).all()
    assert not t.used[0, 0, 4] and np.isnan(t.reprojection_px[0, 0, 4])


def test_two_views_that_disagree_and_too_few_views_are_invalid():
    cams = ring(4)
    X = random_points(4, 2, seed=7)
    x = project(cams, X)
    conf = full_conf(4, X)
    conf[2:] = 0.0
    x[1, 0, 0] += 100.0  # two views, one wrong: no way to tell which
    t = triangulate(x, conf, cams)
    assert not t.valid[0, 0] and t.valid.sum() == 7
    t3 = triangulate(project(cams, X), conf, cams, min_views=3)
    assert not t3.valid.any()


def test_point_behind_one_camera_is_not_its_inlier():
    cams = ring(4, radius=3000.0)
    # behind cam0 (on the far side of it from TARGET), in front of the other three
    eye0 = cams[0].center
    X = (TARGET + 1.15 * (eye0 - TARGET) + [0.0, 20.0, 0.0])[None, None]
    assert cams[0].project(X[0])[1][0] < 0 and all(c.project(X[0])[1][0] > 0 for c in cams[1:])
    x = project(cams, X)  # cam0's "detection" is the mirrored projection: the all-view DLT fits it exactly
    t = triangulate(x, full_conf(4, X), cams)
    assert t.valid[0, 0]
    np.testing.assert_allclose(t.points[0, 0], X[0, 0], atol=1e-6, rtol=0)
    assert t.used[0, 0].tolist() == [False, True, True, True]
    assert np.isinf(t.reprojection_px[0, 0, 0]) and (t.reprojection_px[0, 0, 1:] < 1e-6).all()


def test_chunks_give_the_same_result(monkeypatch):
    cams = ring(4)
    X = random_points(9, 5, seed=8)
    x = project(cams, X)
    x[1, ::2] += 50.0
    whole = triangulate(x, full_conf(4, X), cams)
    monkeypatch.setattr(tri_mod, "_CHUNK", 7)
    parts = triangulate(x, full_conf(4, X), cams)
    np.testing.assert_array_equal(whole.valid, parts.valid)
    np.testing.assert_array_equal(whole.used, parts.used)
    np.testing.assert_allclose(whole.points, parts.points, atol=1e-9)


def test_summary_keys_and_json():
    cams = ring(4)
    X = random_points(5, 3, seed=9)
    x = project(cams, X)
    x[3, :, 0] += 60.0
    conf = full_conf(4, X)
    conf[:, :, 2] = 0.0  # joint 2 never seen: None statistics
    t = triangulate(x, conf, cams)
    s = reprojection_summary(t, ["head", "l_wrist", "r_wrist"], [c.name for c in cams])
    text = json.dumps(s, allow_nan=False)
    assert json.loads(text) == s
    assert set(s) == {"num_frames", "num_joints", "num_cameras", "triangulated_fraction", "median_px", "p90_px",
                      "per_joint", "per_camera"}
    assert (s["num_frames"], s["num_joints"], s["num_cameras"]) == (5, 3, 4)
    assert s["triangulated_fraction"] == pytest.approx(2 / 3)
    assert set(s["per_joint"]["head"]) == {"median_px", "p90_px", "triangulated_fraction", "inlier_views"}
    assert s["per_joint"]["r_wrist"] == {"median_px": None, "p90_px": None, "triangulated_fraction": 0.0,
                                         "inlier_views": 0}
    assert set(s["per_camera"]["cam0"]) == {"median_px", "p90_px", "detections", "inliers", "rejected_fraction"}
    assert s["per_camera"]["cam3"]["rejected_fraction"] == pytest.approx(0.5)  # joint 0 of 2 seen joints
    assert s["per_camera"]["cam0"] == {"median_px": pytest.approx(0, abs=1e-6), "p90_px": pytest.approx(0, abs=1e-6),
                                       "detections": 10, "inliers": 10, "rejected_fraction": 0.0}
    with pytest.raises(ValueError, match="joint_names"):
        reprojection_summary(t, ["a", "b"], [c.name for c in cams])
    with pytest.raises(ValueError, match="camera_names"):
        reprojection_summary(t, ["a", "b", "c"], ["x", "x", "y", "z"])


def test_argument_errors(unchecked):
    cams = ring(3)
    X = random_points(2, 2)
    x, conf = project(cams, X), full_conf(3, X)
    with pytest.raises(ValueError, match="cameras"):
        triangulate(x, conf, cams[:2])
    with pytest.raises(ValueError, match="min_views"):
        triangulate(x, conf, cams, min_views=1)
    with pytest.raises(ValueError, match="min_conf"):
        triangulate(x, conf, cams, min_conf=0.0)
    with pytest.raises(ValueError, match="max_error_px"):
        triangulate(x, conf, cams, max_error_px=0.0)
    with unchecked(), pytest.raises(ValueError, match="conf"):
        triangulate(x, conf[:, :1], cams)


def test_speed_100_frames_16_joints_4_cameras():
    cams = ring(4)
    X = random_points(100, 16, seed=10)
    x = project(cams, X) + np.random.default_rng(11).normal(0, 1.0, size=(4, 100, 16, 2))
    x[np.arange(100) % 4, np.arange(100)] += 80.0  # every point has one wrong view: all take the robust path
    conf = full_conf(4, X)
    triangulate(x, conf, cams)  # warm-up
    start = time.perf_counter()
    t = triangulate(x, conf, cams)
    assert time.perf_counter() - start < 0.5
    assert t.valid.all() and (t.used.sum(axis=-1) == 3).all()


def test_no_frames_and_a_single_camera():
    cams = ring(3)
    t = triangulate(np.zeros((3, 0, 4, 2)), np.zeros((3, 0, 4)), cams)
    assert t.points.shape == (0, 4, 3) and t.used.shape == (0, 4, 3)
    s = reprojection_summary(t, list("abcd"), [c.name for c in cams])
    assert s["triangulated_fraction"] is None and s["median_px"] is None
    json.dumps(s, allow_nan=False)
    X = random_points(2, 2)
    one = triangulate(project(cams[:1], X), full_conf(1, X), cams[:1])
    assert not one.valid.any() and np.isnan(one.points).all()
