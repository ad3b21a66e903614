"""deliffas.native: every declared C library built at once (the viewer's warm-up), and the C headers as the one
binding table (each library's prototypes, checked by the compiler against the definitions and by ``nm`` against the
exported symbols, and the ctypes signatures declared from them)."""

from __future__ import annotations

import ctypes
import importlib
import os
import re
import shlex
import shutil
import subprocess
import threading
import time

import pytest

from deliffas import native

CALLERS = ("deliffas.fast.shade", "deliffas.fast.rasterize", "deliffas.geometry.sampling",
           "deliffas.geometry.normal_maps", "deliffas.models.encoding", "deliffas.models.feature_sigmoid",
           "deliffas.models.unet_cpu", "deliffas.models.unet_grad")
"""The modules that hold the package's LazyLibrary objects."""

_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]*[<"]([^">]+)[">]', re.M)


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


def _package_libraries() -> list[native.LazyLibrary]:
    """The LazyLibrary objects of the package's modules (imported here, so they are declared)."""
    libs = [value for name in CALLERS for value in vars(importlib.import_module(name)).values()
            if isinstance(value, native.LazyLibrary)]
    assert libs and all(lib in native._DECLARED for lib in libs)
    return libs


def test_every_source_includes_its_own_header_and_no_c_file():
    sources = sorted(native.CSRC.glob("*.c"))
    assert sources
    for path in sources:
        includes = _INCLUDE.findall(path.read_text(encoding="utf-8"))
        assert includes[:1] == [f"{path.stem}.h"], f"{path.name} includes {includes}: its own header must be first"
        assert (native.CSRC / f"{path.stem}.h").is_file()
    for path in [*sources, *native.CSRC.glob("*.h")]:
        included_c = [name for name in _INCLUDE.findall(path.read_text(encoding="utf-8")) if name.endswith(".c")]
        assert not included_c, f"{path.name} includes the C file(s) {included_c}; share code through a header"


def test_every_declared_library_has_a_header_that_parses():
    libs = _package_libraries()
    assert sorted(lib.source for lib in libs) == sorted(p.name for p in native.CSRC.glob("*.c"))  # each .c a library
    for lib in libs:
        assert lib.header == lib.source.removesuffix(".c") + ".h"
        prototypes = native.c_prototypes((native.CSRC / lib.header).read_text(encoding="utf-8"), lib.header)
        assert prototypes, f"{lib.header} declares no function"
        for name, proto in prototypes.items():
            assert name == proto.name and name.startswith("deliffas_"), proto.text
            assert proto.restype in native._C_TYPES.values() or proto.restype is ctypes.c_void_p, proto.text
            assert all(t in native._C_TYPES.values() or t is ctypes.c_void_p for t in proto.argtypes), proto.text
            assert None not in proto.argtypes, proto.text


def _compiler() -> list[str]:
    """The compiler build_library uses (skips the test when there is none, or when compiling is disabled)."""
    if os.environ.get(native.NATIVE_ENV, "1").strip() == "0":
        pytest.skip(f"compiled kernels disabled by {native.NATIVE_ENV}=0")
    cc = shlex.split(os.environ.get("CC", "")) or [shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")]
    if not cc[0]:
        pytest.skip("no C compiler (cc, gcc or clang on PATH, or $CC)")
    if shutil.which("nm") is None:
        pytest.skip("nm is not on PATH")
    return cc


def _build(cc: list[str], lib: native.LazyLibrary, out) -> None:
    """``lib`` compiled as build_library compiles it (with -march=native, else without), into the file ``out``."""
    errors = []
    for arch in (("-march=native",), ()):
        cmd = [*cc, *native.BASE_FLAGS, *lib.flags, *arch, str(native.CSRC / lib.source), "-o", str(out)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if proc.returncode == 0:
            return
        errors.append(proc.stderr[-2000:])
    pytest.fail(f"{lib.source} does not compile: {errors[-1]}")


def test_exported_symbols_and_declared_signatures_are_the_headers(tmp_path, monkeypatch):
    cc = _compiler()
    for lib in _package_libraries():
        path = tmp_path / f"{lib.name}.so"
        _build(cc, lib, path)
        nm = subprocess.run(["nm", "-D", "--defined-only", str(path)], capture_output=True, text=True, check=True)
        exported = {line.split()[-1] for line in nm.stdout.splitlines() if line.strip()}
        prototypes = native.c_prototypes((native.CSRC / lib.header).read_text(encoding="utf-8"), lib.header)
        assert {s for s in exported if s.startswith("deliffas_")} == set(prototypes), lib.source
        loaded = ctypes.CDLL(str(path))
        monkeypatch.setattr(native, "build_library", lambda name, source, flags=(): native.NativeLibrary(loaded))
        monkeypatch.setattr(native, "_DECLARED", [])
        declared = native.LazyLibrary(lib.name, lib.source, lib.flags, fallback="none").load().lib
        assert declared is loaded
        for proto in prototypes.values():
            fn = getattr(declared, proto.name)
            assert list(fn.argtypes) == list(proto.argtypes) and fn.restype is proto.restype, proto.text


def test_a_library_without_its_headers_functions_is_unavailable(monkeypatch):
    libc = ctypes.CDLL(None)  # the process itself: no deliffas_ function
    monkeypatch.setattr(native, "build_library", lambda name, source, flags=(): native.NativeLibrary(libc))
    monkeypatch.setattr(native, "_DECLARED", [])
    missing = native.LazyLibrary("encoding_test", "encoding.c", fallback="none").load()
    assert missing.lib is None and "lacks a symbol" in missing.reason and "deliffas_encode_parts_f32" in missing.reason
    unparsed = native.LazyLibrary("bad_header", "ray_inputs.c", header="fused_tiles.h", fallback="none").load()
    assert unparsed.lib is None and "fused_tiles.h" in unparsed.reason and "not a function prototype" in unparsed.reason
    absent = native.LazyLibrary("no_header", "ray_inputs.c", header="no_such_header.h", fallback="none").load()
    assert absent.lib is None and "no_such_header.h" in absent.reason


def test_the_prototype_parser_on_small_examples():
    text = """/* a comment with int f(void); inside */
    #ifndef X_H
    #define X_H \\
        1
    #include <stdint.h>
    typedef struct { const float *p; int64_t n; } pair;
    int64_t count(const float *restrict values, int64_t n, float *const *out);  // trailing comment
    void   fill(const float *const *xs, int32_t parts, uint8_t flag, double scale, float eps, int bf16);
    int ready(void);
    void *raw(void);
    #endif
    """
    protos = native.c_prototypes(text, "example.h")
    assert list(protos) == ["count", "fill", "ready", "raw"]
    p, i32, i64 = ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64
    assert protos["count"].argtypes == (p, i64, p) and protos["count"].restype is i64
    assert protos["fill"].argtypes == (p, i32, ctypes.c_uint8, ctypes.c_double, ctypes.c_float, i32)
    assert protos["fill"].restype is None
    assert protos["ready"].argtypes == () and protos["ready"].restype is i32
    assert protos["raw"].argtypes == () and protos["raw"].restype is p
    assert protos["count"].text == "int64_t count(const float *restrict values, int64_t n, float *const *out)"
    with pytest.raises(ValueError, match=r"example\.h: .*size_t.*unsupported C type 'size_t'"):
        native.c_prototypes("int64_t total(const float *x, size_t n);", "example.h")
    with pytest.raises(ValueError, match=r"example\.h: .*unsupported C type 'unsigned long'"):
        native.c_prototypes("unsigned long total(const float *x);", "example.h")
    with pytest.raises(ValueError, match=r"example\.h: not a function prototype: 'static const int table"):
        native.c_prototypes("static const int table[2] = {1, 2};", "example.h")
