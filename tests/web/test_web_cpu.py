"""The player's CPU backend (``?backend=cpu``, and the automatic fallback where the browser has no WebGL2): its
frames against ``deliffas render``'s, as the WebGL2 backend's in test_web_browser.py."""

from __future__ import annotations

import pytest

from deliffas.engine.export_config import ExportConfig
from deliffas.engine.web import export_web
from deliffas.models.model_table import DEFAULT_MODEL, DEFAULT_PRESET

from test_web_browser import AGREEMENT_DB, CAMERAS, DOWNSAMPLED, FRAMES
from web_page import needs_chromium, page_frame, person_scores, reference_frames, served_page

NO_WEBGL2 = """(() => {
  const get = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (kind, ...rest) {
    return kind === 'webgl2' ? null : get.call(this, kind, ...rest);
  };
})();"""
"""An init script that makes the browser one without WebGL2."""


@needs_chromium
@pytest.mark.parametrize("model, preset, overrides",
                         [pytest.param(DEFAULT_MODEL, DEFAULT_PRESET, {}, id="default"),
                          pytest.param(DEFAULT_MODEL, "realtime", {}, id="realtime"),
                          pytest.param("single_surface_viewdir", "tiny", {}, id="single_surface_viewdir"), DOWNSAMPLED])
def test_the_cpu_backend_agrees_with_deliffas_render(web_capture, web_runs, tmp_path, model, preset, overrides):
    run = web_runs(model, preset, **overrides)
    motion = next((web_capture[0] / "testing").glob("*.motion"))
    out = export_web(ExportConfig(run=run, out=tmp_path / "page", web=True, motion=motion))
    refs = {c: reference_frames(run, motion, c, FRAMES, tmp_path / f"ref{c}") for c in CAMERAS}
    with served_page(out, tmp_path, query="?backend=cpu") as page:
        scores = person_scores(page, refs)
        stats = page.evaluate("() => window.deliffasPlayer.stats()")
        hits = page.evaluate("() => window.deliffasPlayer.hits()")
        shown = page.evaluate("() => document.getElementById('fps').textContent")
    print(f"cpu backend, {model} {preset} {overrides}: PSNR on the person (dB) {scores}")  # shown with pytest -s
    assert min(scores.values()) >= AGREEMENT_DB, scores
    assert stats["backend"] == "cpu" and set(stats["stages_ms"]) >= {"unet", "raster", "shade"}
    assert "cpu" in shown
    h, w = refs[CAMERAS[-1]][0].shape[:2]
    assert set(hits) == {"inner", "outer", "exit"} and all(len(v) == h * w * 4 for v in hits.values())


@needs_chromium
def test_without_webgl2_the_page_falls_back_to_the_cpu(web_runs, tmp_path):
    out = export_web(ExportConfig(run=web_runs(DEFAULT_MODEL, DEFAULT_PRESET), out=tmp_path / "page", web=True))
    with served_page(out, tmp_path, init_script=NO_WEBGL2) as page:
        assert page.evaluate("() => window.deliffasPlayer.stats().backend") == "cpu"
        assert page_frame(page, 0, 0).max() > 0  # the person is drawn
    forced = tmp_path / "forced"
    forced.mkdir()
    with served_page(out, forced, init_script=NO_WEBGL2, query="?backend=webgl2", expect_ready=False) as page:
        ok = page.evaluate("() => window.deliffasPlayer.ready.then(() => true, e => String(e))")
        assert ok is not True and "no WebGL2" in page.locator("#message").text_content()
    with served_page(out, forced, query="?backend=webgl2") as page:
        assert page.evaluate("() => window.deliffasPlayer.stats().backend").startswith("webgl2")
