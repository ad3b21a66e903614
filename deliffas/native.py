"""Small C kernels compiled at first use with the system C compiler and loaded through ctypes.

The C sources are package data in ``deliffas/csrc/`` (:data:`CSRC`): the rasteriser and the shading passes of
the real-time path (``deliffas/fast/``), the fused normal-map gather (``geometry/normal_maps.py``), the
training's bilinear feature gather (``geometry/sampling.py``), the MLP's positional encodings
(``models/encoding.py``), the U-Nets' training sigmoid with its saturation penalty (``models/feature_sigmoid.py``),
their final layer's gradients (``models/unet_grad.py``) and the U-Net's input conversion (``models/unet_cpu.py``).
Each library is built once per process, with ``-march=native`` first (the build machine is the run machine) and
portable flags if that fails, from ``$CC`` or the first of ``cc``, ``gcc``, ``clang`` on PATH, into a temporary
directory that is removed after loading (the library stays mapped). Nothing is cached on disk.

Callers hold a :class:`LazyLibrary`, which builds on first use and logs once when it falls back.
:func:`build_declared` builds every library declared so far at once (the viewer, before its first frame).
Set ``DELIFFAS_NATIVE=0`` to never compile; every caller then keeps a pure-torch fallback.
"""

from __future__ import annotations

import ctypes
import logging
import os
import shlex
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

__all__ = ["CSRC", "NATIVE_ENV", "LazyLibrary", "NativeLibrary", "build_library", "build_declared"]

logger = logging.getLogger(__name__)

NATIVE_ENV = "DELIFFAS_NATIVE"
"""Environment variable: "0" disables every compiled kernel."""

BASE_FLAGS = ("-O3", "-std=c99", "-fPIC", "-shared")

CSRC = Path(__file__).with_name("csrc")
"""The folder of the package's C sources (shipped in the wheel as package data)."""


@dataclass(frozen=True)
class NativeLibrary:
    """The outcome of one build.

    Attributes:
        lib: the loaded library, or None when unavailable.
        reason: why it is unavailable ("" when loaded).
        build_seconds: compiler run(s) and load, wall time.
        command: the compiler command that built it, without temporary paths ("" when not built).
    """

    lib: ctypes.CDLL | None
    reason: str = ""
    build_seconds: float = 0.0
    command: str = ""


def build_library(name: str, source: str, flags: Sequence[str] = ()) -> NativeLibrary:
    """Compile the C file ``source`` of :data:`CSRC` into a shared library and load it.

    Args:
        name: library stem (for messages and the temporary file names).
        source: file name in :data:`CSRC` (C99; a quoted ``#include`` finds its siblings there).
        flags: compiler flags added to ``-O3 -std=c99 -fPIC -shared``.

    Returns:
        NativeLibrary; ``lib`` is None (with the reason) when disabled, when no compiler is found,
        or when compiling or loading fails. Never raises for those.
    """
    if os.environ.get(NATIVE_ENV, "1").strip() == "0":
        return NativeLibrary(None, f"disabled by {NATIVE_ENV}=0")
    cc = shlex.split(os.environ.get("CC", "")) or [shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")]
    if not cc[0]:
        return NativeLibrary(None, "no C compiler found (cc, gcc or clang on PATH, or $CC)")
    t0 = time.perf_counter()
    errors = []
    with tempfile.TemporaryDirectory(prefix=f"deliffas_{name}_", ignore_cleanup_errors=True) as tmp:
        src, lib_path = CSRC / source, Path(tmp) / f"{name}.so"
        for arch in (("-march=native",), ()):
            cmd = [*cc, *BASE_FLAGS, *flags, *arch, str(src), "-o", str(lib_path)]
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
            except (OSError, subprocess.SubprocessError) as exc:
                errors.append(f"{type(exc).__name__}: {exc}")
                continue
            if proc.returncode == 0:
                break
            errors.append((proc.stderr or proc.stdout).strip()[-400:])
        else:
            return NativeLibrary(None, f"{' '.join(cc)} failed: {errors[-1]}")
        try:
            lib = ctypes.CDLL(str(lib_path))  # stays mapped after the directory is removed
        except OSError as exc:
            return NativeLibrary(None, f"loading the built {name} library failed: {exc}")
    command = " ".join([*cmd[:-3], source])
    return NativeLibrary(lib, "", time.perf_counter() - t0, command)


class LazyLibrary:
    """A C library built on first use, once per process (thread-safe), for one caller.

    Args:
        name: library stem and the name in log messages.
        source: file name in :data:`CSRC`.
        flags: extra compiler flags (see :func:`build_library`).
        setup: called once with the loaded library to declare its ctypes signatures; an
            ``AttributeError`` (a missing symbol) makes the library unavailable.
        fallback: what the caller uses without it, for the log message.
    """

    def __init__(self, name: str, source: str, flags: Sequence[str] = (), *,
                 setup: Callable[[ctypes.CDLL], None] | None = None, fallback: str) -> None:
        self.name, self.source, self.flags = name, source, tuple(flags)
        self.setup, self.fallback = setup, fallback
        self._lock = threading.Lock()
        self._built: NativeLibrary | None = None
        self._logged = False
        _DECLARED.append(self)

    def load(self) -> NativeLibrary:
        """The outcome of the build, building on the first call."""
        if self._built is None:
            with self._lock:
                if self._built is None:
                    built = build_library(self.name, self.source, self.flags)
                    if built.lib is not None and self.setup is not None:
                        try:
                            self.setup(built.lib)
                        except AttributeError as exc:
                            built = NativeLibrary(None, f"the built {self.name} library lacks a symbol: {exc}")
                    self._built = built
        return self._built

    def get(self) -> ctypes.CDLL | None:
        """The loaded library, or None after logging (once per process) why the fallback is used:
        at INFO when disabled by ``DELIFFAS_NATIVE=0``, else as a WARNING."""
        built = self.load()
        if built.lib is None and not self._logged:
            self._logged = True
            level = logging.INFO if built.reason.startswith("disabled") else logging.WARNING
            logger.log(level, "%s: compiled kernel unavailable (%s); using %s", self.name, built.reason, self.fallback)
        return built.lib


_DECLARED: list[LazyLibrary] = []
"""Every LazyLibrary of the modules imported so far (they are module attributes: created at import)."""


def build_declared() -> None:
    """Build every declared library not built yet, all at once (one thread each, so the compilers run in parallel;
    a first use builds one library after another). What fails to build is reported by its ``get``, as always."""
    threads = [threading.Thread(target=lib.load, name=f"build-{lib.name}", daemon=True) for lib in list(_DECLARED)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
