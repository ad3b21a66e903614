"""The array parts of ``deliffas ingest``: frame plans, masks made consistent, the sequence split, silhouettes."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.io.cameras import Camera, look_at
from deliffas.data.ingest.frames import output_size, plan_frames
from deliffas.data.ingest.masks import person_mask
from deliffas.data.ingest.write import silhouette, split_frames


def _camera(w=1088, h=1920, name="cam01", distortion=None) -> Camera:
    K = np.array([[1600.0, 0, w / 2], [0, 1600.0, h / 2], [0, 0, 1]])
    extra = {"distortion": np.asarray(distortion, np.float64)} if distortion is not None else {}
    return Camera(name, K, look_at([0, 1000, 3000], [0, 1000, 0]), w, h, extra=extra)


def test_output_size_keeps_the_aspect_with_even_sides():
    assert output_size(1080 / 1920, 960) == (540, 960)
    assert output_size(2.0, 100) == (100, 50)
    assert output_size(0.5, (33, 44)) == (33, 44)


def test_a_narrower_stream_is_a_crop_and_cameras_share_one_size():
    cams = [_camera(name="a"), _camera(name="b")]
    plans = plan_frames(cams, [(1080, 1920), (1088, 1920)], ["a.mp4", "b.mp4"], 960)
    assert [p.size for p in plans] == [(540, 960)] * 2
    assert [p.crop for p in plans] == [(1080, 1920)] * 2
    assert "cropped" in plans[0].note and "cropped" in plans[1].note
    for p in plans:  # the crop keeps pixel coordinates; the resize halves them
        assert p.camera.width == 540 and np.isclose(p.camera.K[0, 0], 1600.0 * 540 / 1080)
        assert np.isclose(p.camera.K[0, 2], 544.0 * 0.5)
    img = np.zeros((1920, 1080, 3), np.uint8)
    assert plans[0](img).shape == (960, 540, 3)


def test_a_stream_of_another_resolution_is_scaled_and_a_wrong_one_refused():
    (p,) = plan_frames([_camera()], [(544, 960)], ["a.mp4"], (544, 960))
    assert "scaled" in p.note and np.isclose(p.camera.K[0, 0], 800.0)
    with pytest.raises(ValueError, match="a.mp4.*1920x1080.*cam01"):
        plan_frames([_camera()], [(1920, 1080)], ["a.mp4"], 960)


def test_distortion_is_removed_from_the_images_and_the_camera():
    K = np.array([[100.0, 0, 100], [0, 100.0, 50], [0, 0, 1]])
    cam = Camera("c", K, np.eye(4), 200, 100, extra={"distortion": np.array([0.2, 0, 0, 0, 0.0])})
    (p,) = plan_frames([cam], [(200, 100)], ["a.mp4"], (200, 100))
    assert p.maps is not None and "distortion" not in p.camera.extra
    # a point projected with the lens model lands where the pinhole camera projects it, after undistortion
    img = np.zeros((100, 200, 3), np.uint8)
    import cv2

    K = cam.K.copy()
    K[:2, 2] -= 0.5
    x = np.array([[[0.6, 0.3, 1.0]]])
    d, _ = cv2.projectPoints(x, np.zeros(3), np.zeros(3), K, np.array([0.2, 0, 0, 0, 0.0]))
    u, v = np.round(d.ravel()).astype(int)
    img[v, u] = 255
    out = p(img)
    peak = np.unravel_index(np.argmax(out[..., 0]), out.shape[:2])
    want = K @ x.ravel()
    assert abs(peak[1] - want[0]) <= 1.5 and abs(peak[0] - want[1]) <= 1.5


def test_person_mask_keeps_the_component_where_the_person_projects():
    prob = np.zeros((100, 100), np.float32)
    prob[10:40, 10:30] = 0.9  # the person
    prob[60:95, 60:90] = 0.95  # a larger bystander
    alpha = person_mask(prob, np.array([[20.0, 25.0]]))
    assert alpha[25, 20] == round(0.9 * 255) and alpha[80, 70] == 0
    largest = person_mask(prob, None)
    assert largest[80, 70] > 0 and largest[25, 20] == 0
    assert not person_mask(np.zeros((8, 8), np.float32), None).any()


def test_split_frames_holds_out_the_last_fraction():
    assert split_frames(range(10), 0.2) == {"training": list(range(8)), "testing": [8, 9]}
    assert split_frames(range(10), 0.0) == {"training": list(range(10))}
    assert split_frames([5], 0.5) == {"training": [5]}


def test_silhouette_fills_a_triangle_in_front_of_the_camera():
    cam = Camera("c", np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]), np.eye(4), 100, 100)
    verts = np.array([[-100.0, -100, 1000], [100, -100, 1000], [0, 100, 1000]])
    sil = silhouette(verts, np.array([[0, 1, 2]]), cam)
    assert sil[50, 50] and not sil[5, 5] and 0.015 < sil.mean() < 0.03
    assert not silhouette(verts * [1, 1, -1], np.array([[0, 1, 2]]), cam).any()
