"""deliffas view SUBJECT: the capture viewer's core (overlay, IoU, posed template), its CLI, and the served page."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from deliffas.data.check import CheckConfig, check_subject
from deliffas.data.check_report import overlay
from deliffas.data.subjects import parse_subject
from deliffas.engine.view import SubjectViewConfig
from deliffas.engine.view.subject import SubjectView, is_capture

from view_browser import needs_chromium, viewer_page

REPO = Path(__file__).resolve().parents[2]

SIZE = 48


def _texel_centres(shot: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The background image of a canvas screenshot at its texel centres, (h, w, 3) float in [0, 1]: the
    overlay (w, h) padded by ``compose_panels`` to the canvas aspect, stretched over the canvas (bilinear
    magnification blurs between texels, so texel centres are compared)."""
    H, W = shot.shape[:2]
    w, h = size
    out_w = max(w, round(h * W / H))  # compose_panels, one panel on a wider canvas
    x0 = (out_w - w) // 2
    xs = ((x0 + np.arange(w) + 0.5) * W / out_w).astype(int)
    ys = ((np.arange(h) + 0.5) * H / h).astype(int)
    return shot[ys][:, xs].astype(np.float32) / 255


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """A tiny synthetic capture: 2 training + 1 testing frames, 3 cameras (camera 1 held out), 48 x 48."""
    from deliffas.data.synth import SynthConfig, synthesize_capture

    out = tmp_path_factory.mktemp("view_subject") / "subject"
    synthesize_capture(out, SynthConfig(num_frames=2, num_cameras=3, width=SIZE, height=SIZE, seed=0))
    return out


@pytest.fixture(scope="module")
def subject_view(capture):
    view = SubjectView(parse_subject(capture), max_side=SIZE)
    yield view
    view.close()


def test_overlay_and_iou_as_check_finds(subject_view, capture):
    v = subject_view
    assert v.num_frames == 3 and v.timeline[0] == ("training", 0) and v.test_cameras == (1,)
    assert v.camera_label(1).endswith("(test)")
    ious = []
    for cam in range(len(v.cameras)):
        o = v.overlay(0, cam)
        assert o.image.shape == (SIZE, SIZE, 3) and o.image.dtype == np.uint8
        assert o.silhouette.shape == o.mask.shape == (SIZE, SIZE) and o.silhouette.any()
        rgb, mask = v.frame_image(0, cam)
        np.testing.assert_array_equal(o.image, overlay(rgb, o.silhouette, mask))  # the check's picture
        ious.append(o.iou)
    assert min(ious) >= 0.95, ious
    checked = check_subject(parse_subject(capture), CheckConfig(max_side=SIZE))
    assert checked.ok and np.all(checked.camera_iou >= 0.95)
    assert v.frame_image(0, 0, 16)[0].shape == (16, 16, 3)  # frustum textures


def test_frames_change_the_mesh_and_the_overlay(subject_view):
    v = subject_view
    a, b = v.posed(0), v.posed(1)
    assert a.shape == b.shape and a.shape[1] == 3
    assert np.abs(a - b).max() > 1.0  # mm
    assert v.posed(0) is a  # cached
    assert not np.array_equal(v.overlay(0, 0).silhouette, v.overlay(1, 0).silhouette)
    assert v.posed(99) is v.posed(v.num_frames - 1)  # clamped to the timeline
    assert np.isclose(np.linalg.norm(v.up_direction()), 1.0)


def test_config_detection_and_cli_errors(capture, tmp_path):
    with pytest.raises(ValueError, match="port must be in"):
        SubjectViewConfig(subject="s", port=70000)
    assert SubjectViewConfig(subject="s", host="0.0.0.0").exposed and not SubjectViewConfig(subject="s").exposed
    assert is_capture(capture) and not is_capture(tmp_path / "missing")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "train_config.json").write_text("{}")
    assert not is_capture(tmp_path / "run")
    (tmp_path / "empty").mkdir()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    for argv, needle in (([str(tmp_path / "empty")], "not a capture of any known format"),
                         ([str(capture), "--motion", "m.motion"], "--motion apply to a run"),
                         ([str(tmp_path / "run"), "--format", "zju"], "--format and --template apply to a capture")):
        res = subprocess.run([sys.executable, "-m", "deliffas", "view", *argv], capture_output=True, text=True,
                             env=env, timeout=120)
        assert res.returncode == 2, res.stderr
        errors = [line for line in res.stderr.splitlines() if "error:" in line]
        assert len(errors) == 1 and needle in errors[0], res.stderr


@needs_chromium
def test_browser_camera_menu_shows_the_overlay(capture, subject_view, tmp_path):
    pytest.importorskip("viser")
    import cv2

    cam = 2
    expected = subject_view.overlay(0, cam)
    ref = expected.image.astype(np.float32) / 255  # what the background must show
    fg = ref.max(-1) > 0.05  # silhouette, mask edge and the darkened image (the capture's background is black)
    assert fg.mean() > 0.05
    # 1200 px wide: the centred capture image clears the GUI panel (right) and the WebGL notice (left)
    with viewer_page([capture, "--resolution", SIZE], tmp_path, (1200, 500)) as page:
        page.locator("input[value='free camera']").first.click()  # the capture camera menu
        page.get_by_role("option", name=subject_view.camera_label(cam), exact=True).click()
        canvas = page.locator("canvas").first

        def matches(panel):  # on the overlay's non-black pixels (the rest would match an empty canvas)
            err = np.abs(panel - ref).max(-1)
            return float(np.median(err[fg])) < 0.06 and float((err[fg] < 0.15).mean()) > 0.9

        deadline, panel, shot = time.time() + 60, None, None
        while time.time() < deadline:
            shot = cv2.cvtColor(cv2.imdecode(np.frombuffer(canvas.screenshot(), np.uint8), cv2.IMREAD_COLOR),
                                cv2.COLOR_BGR2RGB)
            panel = _texel_centres(shot, (SIZE, SIZE))
            if matches(panel):
                break
            time.sleep(0.5)
        cv2.imwrite(str(tmp_path / "viewer.png"), cv2.cvtColor(shot, cv2.COLOR_RGB2BGR))
        err = np.abs(panel - ref).max(-1)[fg]
        assert matches(panel), (f"background differs from the overlay: median {np.median(err):.3f}, "
                                f"within 0.15: {(err < 0.15).mean():.2f}; screenshot {tmp_path / 'viewer.png'}; server log:\n"
                                f"{(tmp_path / 'view.log').read_text()[-2000:]}")
        field = page.locator(f"input[value^='{expected.iou:.3f} (']")  # the IoU text field
        deadline = time.time() + 20
        while field.count() != 1 and time.time() < deadline:
            time.sleep(0.25)
        assert field.count() == 1, "the IoU field does not show the camera's IoU"
