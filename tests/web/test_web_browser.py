"""The exported page in headless Chromium (software WebGL2): its frames against ``deliffas render``'s, the orbit
view and its controls, and the message a page opened from ``file://`` shows."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.engine.export_config import ExportConfig
from deliffas.engine.web import export_web
from deliffas.models.model_table import DEFAULT_MODEL, DEFAULT_PRESET

from web_page import needs_chromium, person_psnr, person_scores, reference_frames, served_page

FRAMES, CAMERAS = 3, (0, 3)  # three frames of the test motion from a training and the held-out camera
AGREEMENT_DB = 35.0  # issue 51's bar; the page reaches about 60 dB here (8-bit rounding)

DOWNSAMPLED = pytest.param(DEFAULT_MODEL, "tiny", {"unet_downsample": 2}, id="unet_downsample_2")
"""The default model with its U-Nets at half the atlas side (feature maps S / 2, texture atlases and normals S)."""
MODELS = [pytest.param(DEFAULT_MODEL, DEFAULT_PRESET, {}, id="default"),
          pytest.param(DEFAULT_MODEL, "realtime", {}, id="realtime"),
          pytest.param("two_surface", "tiny", {}, id="two_surface"),
          pytest.param("single_surface_viewdir", "tiny", {}, id="single_surface_viewdir"), DOWNSAMPLED]


@needs_chromium
@pytest.mark.parametrize("model, preset, overrides", MODELS)
def test_page_frames_agree_with_deliffas_render(web_capture, web_runs, tmp_path, model, preset, overrides):
    run = web_runs(model, preset, **overrides)
    motion = next((web_capture[0] / "testing").glob("*.motion"))
    out = export_web(ExportConfig(run=run, out=tmp_path / "page", web=True, motion=motion))
    refs = {c: reference_frames(run, motion, c, FRAMES, tmp_path / f"ref{c}") for c in CAMERAS}
    with served_page(out, tmp_path) as page:
        scores = person_scores(page, refs)
        stats = page.evaluate("() => window.deliffasPlayer.stats()")
    print(f"{model} {preset} {overrides}: PSNR on the person (dB) {scores}")  # shown with pytest -s
    assert min(scores.values()) >= AGREEMENT_DB, scores
    assert stats["backend"].startswith("webgl2") and set(stats["stages_ms"]) >= {"unet", "raster", "shade"}


@needs_chromium
def test_the_page_plays_and_its_orbit_turns(web_runs, tmp_path):
    out = export_web(ExportConfig(run=web_runs("two_surface", "tiny"), out=tmp_path / "page", web=True))
    with served_page(out, tmp_path) as page:
        shot = lambda: page.evaluate("() => document.getElementById('view').toDataURL()")  # noqa: E731
        page.wait_for_function("() => window.deliffasPlayer.stats().fps > 0")
        page.click("#play")  # pause
        page.select_option("#camera", "orbit")
        before = shot()
        box = page.locator("#view").bounding_box()
        page.mouse.move(box["x"] + 20, box["y"] + 20)
        page.mouse.down()
        page.mouse.move(box["x"] + 80, box["y"] + 30, steps=4)
        page.mouse.up()
        assert shot() != before, "dragging did not turn the orbit camera"
        page.locator("#frame").fill("2")
        assert page.evaluate("() => document.getElementById('fps').textContent").find("frame 3/") >= 0


@needs_chromium
def test_a_page_opened_from_a_file_says_how_to_serve_it(web_runs, tmp_path):
    out = export_web(ExportConfig(run=web_runs("two_surface", "tiny"), out=tmp_path / "page", web=True))
    with served_page(out, tmp_path, url=(out / "index.html").as_uri()) as page:
        message = page.locator("#message")
        assert message.is_visible() and "python -m http.server" in message.text_content()


@needs_chromium
def test_the_page_poses_an_lbs_template_as_deliffas_does(tmp_path):
    """The page's posed surfaces and normal maps against ``deliffas.geometry``'s for a template skinned by LBS (the
    captures above use DQS, the synthetic default)."""
    import torch

    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.pose_motions import read_pose_motion
    from deliffas.data.synth import SynthConfig, synthesize_capture
    from deliffas.engine.avatar import run_capture
    from deliffas.engine.render import motion_geometry_builder
    from deliffas.engine.train import TrainConfig, train

    synthesize_capture(tmp_path / "subject", SynthConfig(num_frames=3, num_test_frames=3, num_cameras=4, width=32,
                                                         height=32, test_cameras=(3,), seed=1, skinning="lbs"))
    convert(tmp_path / "subject", tmp_path / "shards", ConvertConfig(atlas_res=16, progress=False))
    train(TrainConfig(shards=str(tmp_path / "shards"), out=str(tmp_path / "run"), model="two_surface", preset="tiny",
                      iters=1, num_workers=0, checkpoint_every=1, preview_every=0, progress=False))
    out = export_web(ExportConfig(run=tmp_path / "run", out=tmp_path / "page", web=True))
    meta, _ = run_capture(tmp_path / "run")
    template, builder = motion_geometry_builder(meta)
    motion = read_pose_motion(next((tmp_path / "subject" / "testing").glob("*.motion")), meta.template_spec(),
                              template.num_dofs)
    geo = builder.build(template.pose(torch.as_tensor(motion.dofs)).numpy())
    with served_page(out, tmp_path) as page:
        for f in range(3):
            got = page.evaluate("f => window.deliffasPlayer.geometry(f)", f)
            assert np.abs(np.reshape(got["inner"], (-1, 3)) - geo.inner[f]).max() < 1e-2  # mm
            assert np.abs(np.reshape(got["outer"], (-1, 3)) - geo.outer[f]).max() < 1e-2
            assert np.abs(np.reshape(got["nmInner"], (3, 16, 16)) - geo.normal_maps_inner[f].numpy()).max() < 1e-4


def test_person_psnr_counts_the_pixels_either_image_paints():
    a = np.zeros((4, 4, 3), np.uint8)
    b = a.copy()
    a[0, 0] = 255
    assert person_psnr(a, b) == pytest.approx(0.0) and person_psnr(a, a) == float("inf")
