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


def _compiler(nm: bool = True) -> list[str]:
    """The compiler build_library uses (skips the test when there is none, or when compiling is disabled, or without
    ``nm`` on PATH where ``nm``)."""
    if os.environ.get(native.NATIVE_ENV, "1").strip() == "0":
        pytest.skip(f"compiled kernels disabled by {native.NATIVE_ENV}=0")
    cc = shlex.split(os.environ.get("CC", "")) or [shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")]
    if not cc[0]:
        pytest.skip("no C compiler (cc, gcc or clang on PATH, or $CC)")
    if nm and shutil.which("nm") is None:
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


STRUCT_CALLS = {"fused_shade.h": "deliffas_fused_shade_args", "rasterize.h": "deliffas_raster_uv_args"}
"""The structures that replaced long argument lists, by header: each with its layout function ``<name>_layout``."""


def test_argument_structures_have_the_compilers_layout(tmp_path):
    cc = _compiler(nm=False)
    checked = {}
    for lib in _package_libraries():
        structs = native.header_structs(lib.header)
        prototypes = native.c_prototypes((native.CSRC / lib.header).read_text(encoding="utf-8"), lib.header)
        layouts = [name for name in structs if f"{name}_layout" in prototypes]
        if not layouts:
            continue
        path = tmp_path / f"{lib.name}.so"
        _build(cc, lib, path)
        loaded = ctypes.CDLL(str(path))
        for name in layouts:
            struct, fn = structs[name], getattr(loaded, f"{name}_layout")
            fn.argtypes, fn.restype = [ctypes.c_void_p], ctypes.c_int64
            count = fn(None)
            assert count == 1 + len(struct._fields_), f"{name}: the C layout has {count - 1} fields"
            values = (ctypes.c_int64 * count)()
            assert fn(values) == count
            offsets = {field: getattr(struct, field).offset for field, _ in struct._fields_}
            assert values[0] == ctypes.sizeof(struct), f"{name}: sizeof {values[0]} in C, {ctypes.sizeof(struct)} here"
            assert list(values[1:]) == list(offsets.values()), f"{name}: C offsets {list(values[1:])}, ctypes {offsets}"
            checked[name] = list(values)
        assert native.check_layouts(loaded, lib.header) == {name: checked[name] for name in layouts}
    assert set(STRUCT_CALLS.values()) <= set(checked)


def test_a_structure_whose_layout_differs_is_refused(tmp_path, monkeypatch):
    cc = _compiler(nm=False)
    lib = next(lib for lib in _package_libraries() if lib.header == "rasterize.h")
    _build(cc, lib, tmp_path / "rasterize.so")
    loaded = ctypes.CDLL(str(tmp_path / "rasterize.so"))
    text = (native.CSRC / "rasterize.h").read_text(encoding="utf-8")
    assert "const double *m;" in text
    text = text.replace("const double *m;", "const double *m, *m2;")  # a field ctypes has and the compiler has not
    monkeypatch.setattr(native, "header_structs", lambda header: native.c_structs(text, header))
    with pytest.raises(ValueError, match=r"rasterize\.h: struct deliffas_raster_uv_args: the compiler's layout"):
        native.check_layouts(loaded, "rasterize.h")
    monkeypatch.setattr(native, "build_library", lambda name, source, flags=(): native.NativeLibrary(loaded))
    monkeypatch.setattr(native, "_DECLARED", [])
    refused = native.LazyLibrary("rasterize_test", "rasterize.c", fallback="none").load()
    assert refused.lib is None and "deliffas_raster_uv_args" in refused.reason


def test_the_long_calls_take_their_structure():
    for header, struct in STRUCT_CALLS.items():
        protos = native.c_prototypes((native.CSRC / header).read_text(encoding="utf-8"), header)
        call = protos[struct.removesuffix("_args")]
        assert call.argtypes == (ctypes.c_void_p,) and f"const {struct} *" in call.text, call.text
        assert protos[f"{struct}_layout"].argtypes == (ctypes.c_void_p,)
        assert protos[f"{struct}_layout"].restype is ctypes.c_int64
        fields = native.header_structs(header)[struct]._fields_
        assert all(t in (ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64, ctypes.c_float, ctypes.c_double)
                   for _, t in fields), fields


def test_dir_args_is_parsed_as_the_former_hand_written_structure():
    dir_args = native.header_structs("ray_inputs.h")["dir_args"]
    p, i32, i64 = ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64
    assert dir_args._fields_ == [("viewdir", p), ("normals", p), ("S", i64), ("L", i32), ("include_input", i32)]
    assert ctypes.sizeof(dir_args) == 32
    assert native.header_structs("ray_inputs.h") is native.header_structs("ray_inputs.h")  # parsed once


def test_the_structure_parser_on_small_examples():
    text = """/* typedef struct { int no; } commented; */
    #include <stdint.h>
    typedef struct {
        const float *restrict a, *b;   // two pointers
        float *const *c;
        int64_t n;
        double scale;
        int32_t x, y;
        int flag;
        uint8_t byte;
        float eps;
    } example_args;
    typedef struct tagged { void *p; } tagged_t;
    typedef int64_t index_t;
    int run(const example_args *args);
    """
    structs = native.c_structs(text, "example.h")
    assert list(structs) == ["example_args", "tagged_t"]
    p, i32 = ctypes.c_void_p, ctypes.c_int32
    ex = structs["example_args"]
    assert issubclass(ex, native.HeaderStruct) and ex.__name__ == "example_args"
    assert ex._fields_ == [("a", p), ("b", p), ("c", p), ("n", ctypes.c_int64), ("scale", ctypes.c_double), ("x", i32),
                           ("y", i32), ("flag", i32), ("byte", ctypes.c_uint8), ("eps", ctypes.c_float)]
    assert structs["tagged_t"]._fields_ == [("p", p)]
    assert list(native.c_prototypes(text, "example.h")) == ["run"]
    values = dict(a=1, b=None, c=3, n=-4, scale=0.5, x=6, y=7, flag=1, byte=255, eps=0.25)
    made = ex(**values)
    assert (made.a, made.b, made.n, made.scale, made.byte, made.eps) == (1, None, -4, 0.5, 255, 0.25)
    with pytest.raises(TypeError, match=r"example_args: every field by name; missing \['eps'\], unknown \['epsilon'\]"):
        ex(**{k: v for k, v in values.items() if k != "eps"}, epsilon=0.25)
    with pytest.raises(TypeError):
        ex(1, None, 3)  # positional: refused
    for member, message in [("size_t n;", r"field 'n': unsupported C type 'size_t'"),
                            ("unsigned long a, b;", r"field 'a': unsupported C type 'unsigned long'"),
                            ("void v;", r"field 'v': unsupported C type 'void'"),
                            ("float m[9];", r"unsupported field declaration 'float m\[9\]'"),
                            ("int bits : 3;", r"unsupported field declaration 'int bits : 3'"),
                            ("void (*fn)(int);", r"unsupported field declaration")]:
        with pytest.raises(ValueError, match=r"example\.h: struct bad: " + message):
            native.c_structs(f"typedef struct {{ int64_t ok; {member} }} bad;", "example.h")
    with pytest.raises(ValueError, match=r"example\.h: unsupported structure"):
        native.c_structs("typedef struct { struct { int a; } inner; } nested;", "example.h")
