"""Small C kernels compiled at first use with the system C compiler and loaded through ctypes.

The fused normal-map gather in ``geometry/normal_maps.py`` uses one. Each is built once per
process, with ``-march=native`` first (the build machine is the run machine) and portable flags
if that fails, from ``$CC`` or the first of ``cc``, ``gcc``, ``clang`` on PATH, in a temporary
directory that is removed after loading (the library stays mapped). Nothing is cached on disk.

Set ``DELIFFAS_NATIVE=0`` to never compile; every caller then keeps a pure-torch fallback.
"""

from __future__ import annotations

import ctypes
import os
import shlex
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

__all__ = ["NATIVE_ENV", "NativeLibrary", "build_library"]

NATIVE_ENV = "DELIFFAS_NATIVE"
"""Environment variable: "0" disables every compiled kernel."""

BASE_FLAGS = ("-O3", "-std=c99", "-fPIC", "-shared")


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
    """Compile C ``source`` into a shared library and load it.

    Args:
        name: file stem (for messages and the temporary file names).
        source: C99 source.
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
        src, lib_path = Path(tmp) / f"{name}.c", Path(tmp) / f"{name}.so"
        src.write_text(source)
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
    command = " ".join([*cmd[:-3], f"{name}.c"])
    return NativeLibrary(lib, "", time.perf_counter() - t0, command)
