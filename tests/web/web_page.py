"""An exported web page in headless Chromium, and the reference frames it is compared with.

``served_page(folder, tmp_path)`` serves ``folder`` with Python's ``http.server`` on a free port, opens it in
Debian's Chromium through playwright (software WebGL2: SwiftShader) and yields the page once
``window.deliffasPlayer.ready`` has resolved. ``page_frame(page, frame, camera)`` renders one frame through the
test hook and returns the canvas as an (H, W, 3) uint8 array. ``reference_frames`` renders the same frames with
``deliffas render`` (the run's own renderer), and ``person_psnr`` compares the two on the person's pixels.
"""

from __future__ import annotations

import base64
import functools
import http.server
import shutil
import socket
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

__all__ = ["CHROMIUM", "needs_chromium", "served_page", "page_frame", "reference_frames", "person_psnr"]

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="no Chromium (Debian package 'chromium', scripts/system_deps.sh installs it)")
"""Marks a test that opens the exported page in Chromium."""


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def serve(folder: Path):
    """``folder`` served over HTTP on a free local port; yields the base URL."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", _free_port()),
                                             functools.partial(_Quiet, directory=str(folder)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


@contextmanager
def served_page(folder: Path, tmp_path: Path, url: str | None = None, timeout_ms: int = 120_000, query: str = "",
                init_script: str | None = None, expect_ready: bool = True):
    """The page of ``folder`` (or ``url``) open in headless Chromium, its player ready (else its message fails;
    not checked with ``expect_ready`` False); ``query`` is appended to the page's URL (``?backend=cpu``),
    ``init_script`` runs before the page's scripts."""
    pw = pytest.importorskip("playwright.sync_api")
    with serve(folder) as base, pw.sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(str(tmp_path / "chromium-profile"), executable_path=CHROMIUM,
                                                   args=CHROMIUM_ARGS, headless=True,
                                                   viewport={"width": 900, "height": 700})
        try:
            page = ctx.new_page()
            page.set_default_timeout(timeout_ms)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            if init_script is not None:
                page.add_init_script(init_script)
            page.goto((url or base) + query)
            if url is None and expect_ready:
                ok = page.evaluate("() => window.deliffasPlayer.ready.then(() => true, e => String(e))")
                message = page.locator("#message").text_content()
                assert ok is True and not errors, f"the player did not start: {ok} {errors} {message}"
            yield page
        finally:
            ctx.close()


def page_frame(page, frame: int, camera: int) -> np.ndarray:
    """``window.deliffasPlayer.render({frame, camera})``'s canvas: (H, W, 3) uint8."""
    import cv2

    page.evaluate("args => window.deliffasPlayer.render(args)", {"frame": frame, "camera": camera})
    url = page.evaluate("() => document.getElementById('view').toDataURL('image/png')")
    data = np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8)
    return cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def reference_frames(run: Path, motion: Path, camera: int, frames: int, out: Path) -> list[np.ndarray]:
    """``deliffas render RUN --motion M --camera C --frames N`` as PNG frames: (H, W, 3) uint8 each."""
    import cv2

    from deliffas.engine.render import RenderConfig, render_video

    render_video(RenderConfig(run=str(run), out=str(out), motion=str(motion), camera=camera, frames=frames))
    return [cv2.cvtColor(cv2.imread(str(out / f"{i:06d}.png")), cv2.COLOR_BGR2RGB) for i in range(frames)]


def person_psnr(page: np.ndarray, ref: np.ndarray) -> float:
    """PSNR (dB, 8-bit) over the pixels either image paints (the person; both render the background black)."""
    person = (page.max(-1) > 0) | (ref.max(-1) > 0)
    err = (page.astype(np.float64) - ref)[person] / 255
    mse = float((err ** 2).mean()) if person.any() else 0.0
    return float("inf") if mse == 0 else 10 * np.log10(1 / mse)


def person_scores(page, refs: dict[int, list[np.ndarray]]) -> dict[tuple[int, int], float]:
    """(camera, frame) -> :func:`person_psnr` of the page's canvas against ``refs[camera][frame]``."""
    scores = {}
    for c, frames in refs.items():
        for f, ref in enumerate(frames):
            img = page_frame(page, f, c)
            assert img.shape == ref.shape
            scores[c, f] = person_psnr(img, ref)
    return scores
