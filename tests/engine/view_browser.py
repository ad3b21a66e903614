"""The served viewer in headless Chromium, shared by the browser tests of ``test_view.py`` and ``test_view_subject.py``.

``viewer_page(args, tmp_path, viewport)`` starts ``deliffas view ARGS --port P`` on a free port, opens
the page in Debian's Chromium through playwright (which never downloads a browser) and yields it; on
the way out the browser is closed and the server terminated, the server even when closing the browser
fails (a loaded machine can time that out; a server once leaked for 12 minutes).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

__all__ = ["CHROMIUM", "needs_chromium", "viewer_page"]

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="no Chromium (Debian package 'chromium', scripts/system_deps.sh installs it)")
"""Marks a test that drives the served page in Chromium."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, proc, timeout: float) -> None:
    """Return once ``port`` accepts connections; fail when ``proc`` exits first or ``timeout`` s pass."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"deliffas view exited with {proc.returncode}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise AssertionError(f"deliffas view did not listen on {port} within {timeout} s")


@contextmanager
def viewer_page(view_args: list[str], tmp_path: Path, viewport: tuple[int, int]):
    """Serve ``deliffas view *view_args`` and yield a playwright page showing it (``viewport`` = (width, height)).

    The server's output goes to ``tmp_path / "view.log"``, the browser profile to ``tmp_path / "chromium-profile"``.
    """
    pw = pytest.importorskip("playwright.sync_api")
    port = free_port()
    log = open(tmp_path / "view.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "deliffas", "view", *map(str, view_args), "--port", str(port)],
                            stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONPATH=str(REPO)))
    try:
        wait_port(port, proc, 90)
        with pw.sync_playwright() as p:
            ctx = p.chromium.launch_persistent_context(str(tmp_path / "chromium-profile"), executable_path=CHROMIUM,
                                                       args=CHROMIUM_ARGS, headless=True,
                                                       viewport={"width": viewport[0], "height": viewport[1]})
            try:
                page = ctx.new_page()
                page.set_default_timeout(30_000)
                page.goto(f"http://127.0.0.1:{port}")
                yield page
            finally:
                ctx.close()
    finally:  # the server goes even when closing the browser fails
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
        log.close()
