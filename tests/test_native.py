"""deliffas.native.build_declared: every declared C library built at once (the viewer's warm-up)."""

from __future__ import annotations

import threading
import time

from deliffas import native


def test_build_declared_builds_every_library_at_once(monkeypatch):
    started, lock = [], threading.Lock()

    def slow_build(name, source, flags=()):
        with lock:
            started.append(name)
        time.sleep(1.0)  # a compiler's run
        return native.NativeLibrary(None, f"{name}: not built in this test")

    monkeypatch.setattr(native, "build_library", slow_build)
    monkeypatch.setattr(native, "_DECLARED", [])  # the package's own libraries are not built here
    libs = [native.LazyLibrary(f"test_{i}", "rasterize.c", fallback="none") for i in range(3)]
    assert native._DECLARED == libs
    t0 = time.perf_counter()
    native.build_declared()
    assert time.perf_counter() - t0 < 2.5  # together, not one after another (3 s)
    assert sorted(started) == ["test_0", "test_1", "test_2"]
    assert all(lib.load().reason.endswith("not built in this test") for lib in libs)
    native.build_declared()  # built already: nothing is built twice
    assert len(started) == 3
