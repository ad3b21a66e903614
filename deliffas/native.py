"""Small C kernels compiled at first use with the system C compiler and loaded through ctypes.

The C sources are package data in ``deliffas/csrc/`` (:data:`CSRC`): the rasteriser and the shading passes of
the real-time path (``deliffas/fast/``), the fused normal-map gather (``geometry/normal_maps.py``), the
training's bilinear feature gather (``geometry/sampling.py``), the MLP's positional encodings
(``models/encoding.py``), the U-Nets' training sigmoid with its saturation penalty (``models/feature_sigmoid.py``),
their final layer's gradients (``models/unet_grad.py``) and the U-Net's input conversion (``models/unet_cpu.py``).
Each library is built once per process, with ``-march=native`` first (the build machine is the run machine) and
portable flags if that fails, from ``$CC`` or the first of ``cc``, ``gcc``, ``clang`` on PATH, into a temporary
directory that is removed after loading (the library stays mapped). Nothing is cached on disk.

The headers are the binding table: each library ``<stem>.c`` includes its own ``<stem>.h``, which holds the prototype
of every function it exports (so the compiler refuses a definition that differs), and :func:`declare` sets the ctypes
``argtypes`` / ``restype`` of those functions from the same prototypes (:func:`c_prototypes`); no caller declares a
signature by hand. A function with many arguments takes one pointer to a ``typedef struct { ... } <name>;`` of its
header instead, which :func:`header_structs` parses into a ``ctypes.Structure`` (:func:`c_structs`) that callers fill
by field name (every field, by keyword: :class:`HeaderStruct`); where the header also declares
``int64_t <name>_layout(int64_t *out)`` (``sizeof`` and each field's ``offsetof``, from the compiler), :func:`declare`
refuses a library whose layout differs from the parsed one. Shared static code lives in headers too
(``ray_inputs_impl.h``, ``fused_tiles.h``): no ``.c`` includes another, and a library stays one translation unit.

Callers hold a :class:`LazyLibrary`, which builds on first use, declares its header's signatures and logs once when it
falls back.
:func:`build_declared` builds every library declared so far at once (the viewer, before its first frame).
Set ``DELIFFAS_NATIVE=0`` to never compile; every caller then keeps a pure-torch fallback.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import re
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from deliffas import environment

__all__ = ["CSRC", "NATIVE_ENV", "HeaderStruct", "LazyLibrary", "NativeLibrary", "Prototype", "build_declared",
           "build_library", "c_prototypes", "c_structs", "check_layouts", "declare", "header_structs"]

logger = logging.getLogger(__name__)

NATIVE_ENV = environment.NATIVE_ENV
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
    if environment.native_disabled():
        return NativeLibrary(None, f"disabled by {NATIVE_ENV}=0")
    cc = environment.c_compiler() or [shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")]
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


_C_TYPES: dict[str, type | None] = {"void": None, "int": ctypes.c_int32, "int32_t": ctypes.c_int32,
                                    "int64_t": ctypes.c_int64, "uint8_t": ctypes.c_uint8, "float": ctypes.c_float,
                                    "double": ctypes.c_double}
"""The C types of the prototypes (a pointer of any type is a ``c_void_p``; ``void`` is a return type only)."""

_QUALIFIERS = re.compile(r"\b(?:const|restrict|__restrict__|__restrict|volatile)\b")
_COMMENTS = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
_DIRECTIVES = re.compile(r"^[ \t]*#(?:\\\n|[^\n])*", re.M)
_PROTOTYPE = re.compile(r"(?P<ret>[A-Za-z_][\w \t\n*]*?)\s*\b(?P<name>[A-Za-z_]\w*)\s*\((?P<params>[^()]*)\)", re.S)


@dataclass(frozen=True)
class Prototype:
    """One C function prototype of a header, as ctypes declares it.

    Attributes:
        name: the function's name (its symbol).
        restype: the ctypes return type (None for ``void``).
        argtypes: the ctypes parameter types, in order.
        text: the prototype, comments dropped and white space collapsed.
    """

    name: str
    restype: type | None
    argtypes: tuple[type, ...]
    text: str


def _ctype(decl: str, *, returned: bool, where: str) -> type | None:
    """The ctypes type of one parameter declaration (type and name) or of a return type (type only)."""
    if "*" in decl or "[" in decl:
        return ctypes.c_void_p
    words = _QUALIFIERS.sub(" ", decl).split()
    c_type = " ".join(words if returned or len(words) < 2 else words[:-1])
    if c_type not in _C_TYPES or (c_type == "void" and not returned):
        raise ValueError(f"{where}: unsupported C type {c_type!r} (supported: pointers, {', '.join(_C_TYPES)})")
    return _C_TYPES[c_type]


def _statements(code: str) -> list[str]:
    """The top-level statements of C code without comments and directives (a braced block stays in its statement)."""
    statements, depth, start = [], 0, 0
    for i, char in enumerate(code):
        depth += {"{": 1, "}": -1}.get(char, 0)
        if char == ";" and depth == 0:
            statements.append(" ".join(code[start:i].split()))
            start = i + 1
    if code[start:].strip():
        statements.append(" ".join(code[start:].split()))
    return [s for s in statements if s]


def c_prototypes(header_text: str, header: str = "<header>") -> dict[str, Prototype]:
    """The function prototypes of a C header, by name, for the simple prototypes of :data:`CSRC`'s headers.

    Comments and preprocessor lines are ignored, and so are ``typedef`` and ``struct`` declarations; every other
    top-level statement must be a prototype ``return-type name(parameters)``. Types: any pointer is ``c_void_p``;
    ``int`` and ``int32_t`` are ``c_int32``, ``int64_t`` ``c_int64``, ``uint8_t`` ``c_uint8``, ``float`` ``c_float``,
    ``double`` ``c_double``; a ``void`` return is None and ``(void)`` no parameters.

    Args:
        header_text: the header's text.
        header: its name, for error messages.

    Raises:
        ValueError: naming the header and the prototype, for a statement that is not a prototype or a type not
            listed above.
    """
    code = _DIRECTIVES.sub("", _COMMENTS.sub(" ", header_text))
    prototypes: dict[str, Prototype] = {}
    for text in _statements(code):
        if re.match(r"(?:typedef|struct|union|enum)\b", text):
            continue
        match = _PROTOTYPE.fullmatch(text)
        if match is None:
            raise ValueError(f"{header}: not a function prototype: {text[:200]!r}")
        where = f"{header}: {text}"
        params = match["params"].strip()
        decls = [] if params in ("", "void") else [p.strip() for p in params.split(",")]
        argtypes = tuple(_ctype(d, returned=False, where=where) for d in decls)
        name = match["name"]
        prototypes[name] = Prototype(name, _ctype(match["ret"], returned=True, where=where), argtypes, text)
    return prototypes


def declare(lib: ctypes.CDLL, header: str) -> dict[str, Prototype]:
    """Set ``argtypes`` and ``restype`` of every function of the header ``header`` (a file name in :data:`CSRC`) on
    the loaded library ``lib``, and check its structures' layouts (:func:`check_layouts`); returns the prototypes.

    Raises:
        AttributeError: when the library lacks one of the header's functions.
        OSError: when the header cannot be read. ValueError: when it does not parse (:func:`c_prototypes`,
            :func:`c_structs`), or a structure's layout is not the compiler's.
    """
    prototypes = c_prototypes((CSRC / header).read_text(encoding="utf-8"), header)
    for proto in prototypes.values():
        fn = getattr(lib, proto.name)
        fn.argtypes = list(proto.argtypes)
        fn.restype = proto.restype
    check_layouts(lib, header)
    return prototypes


class HeaderStruct(ctypes.Structure):
    """The base of the Structures parsed from headers (:func:`c_structs`): built from keyword arguments only, one for
    every field (ctypes would leave an omitted field 0 and take a misspelt name as a plain attribute)."""

    def __init__(self, **fields) -> None:
        names = [name for name, _ in self._fields_]
        if set(fields) != set(names):
            missing, unknown = sorted(set(names) - set(fields)), sorted(set(fields) - set(names))
            raise TypeError(f"{type(self).__name__}: every field by name; missing {missing}, unknown {unknown}")
        super().__init__(**fields)


_STRUCT = re.compile(r"typedef struct(?: [A-Za-z_]\w*)? ?\{(?P<body>[^{}]*)\} ?(?P<name>[A-Za-z_]\w*)")
_MEMBER = re.compile(r"(?P<base>[A-Za-z_][\w ]*?) ?(?P<first>\**[ ]?[A-Za-z_]\w*)")
_DECLARATOR = re.compile(r"(?P<stars>\**) ?(?P<name>[A-Za-z_]\w*)")


def _struct_fields(body: str, where: str) -> list[tuple[str, type]]:
    """The ctypes ``_fields_`` of a struct's member declarations (``type a, *b;``: several declarators of one type)."""
    fields: list[tuple[str, type]] = []
    for member in _statements(body):
        text = " ".join(_QUALIFIERS.sub(" ", member).replace("*", " * ").split()).replace("* ", "*")
        match = _MEMBER.fullmatch(text.split(",")[0].strip())
        declarators = [match["first"], *(d.strip() for d in text.split(",")[1:])] if match else []
        parsed = [_DECLARATOR.fullmatch(d) for d in declarators]
        if not parsed or None in parsed:
            raise ValueError(f"{where}: unsupported field declaration {member!r} (one type, then names or pointers; "
                             "no arrays, bit fields, nested or function-pointer members)")
        for decl in parsed:
            c_type = ctypes.c_void_p if decl["stars"] else _C_TYPES.get(match["base"])
            if c_type is None:
                raise ValueError(f"{where}: field {decl['name']!r}: unsupported C type {match['base']!r} "
                                 f"(supported: pointers, {', '.join(t for t in _C_TYPES if t != 'void')})")
            fields.append((decl["name"], c_type))
    return fields


def c_structs(header_text: str, header: str = "<header>") -> dict[str, type[HeaderStruct]]:
    """The ``typedef struct { <type> <name>; ... } <name>;`` blocks of a C header as ctypes Structures (subclasses of
    :class:`HeaderStruct`), by the typedef's name, fields in declaration order with the types of :func:`c_prototypes`
    (any pointer ``c_void_p``, ``int`` / ``int32_t`` ``c_int32``, ``int64_t`` ``c_int64``, ``uint8_t`` ``c_uint8``,
    ``float`` ``c_float``, ``double`` ``c_double``), laid out by ctypes as the platform's C compiler lays them out.
    Other statements (prototypes, other typedefs) are ignored.

    Raises:
        ValueError: naming the header, the structure and the field, for a member of another type or form (arrays,
            bit fields, function pointers); naming the header, for a ``typedef struct`` with nested braces.
    """
    structs: dict[str, type[HeaderStruct]] = {}
    for text in _statements(_DIRECTIVES.sub("", _COMMENTS.sub(" ", header_text))):
        match = _STRUCT.fullmatch(text)
        if match is None and re.match(r"typedef struct\b[^{]*\{", text):
            raise ValueError(f"{header}: unsupported structure (nested braces, or not 'typedef struct {{ ... }} "
                             f"name'): {text[:200]!r}")
        if match is not None:
            name = match["name"]
            fields = _struct_fields(match["body"], f"{header}: struct {name}")
            doc = f"``{name}`` of ``{header}`` (parsed by deliffas.native.c_structs)."
            structs[name] = type(name, (HeaderStruct,), {"_fields_": fields, "__doc__": doc})
    return structs


@functools.lru_cache(maxsize=None)
def header_structs(header: str) -> dict[str, type[HeaderStruct]]:
    """:func:`c_structs` of the header ``header`` (a file name in :data:`CSRC`), parsed once per process (one class per
    structure). Raises OSError or ValueError as reading it or :func:`c_structs` does."""
    return c_structs((CSRC / header).read_text(encoding="utf-8"), header)


def check_layouts(lib: ctypes.CDLL, header: str) -> dict[str, list[int]]:
    """Check each structure ``<name>`` of the header ``header`` whose layout function ``<name>_layout`` the header
    declares against the compiler's layout: the function writes ``sizeof`` and then each field's ``offsetof`` in
    declaration order (with NULL it only returns how many), which must equal ``ctypes.sizeof`` and the Structure's
    field offsets. Returns the layouts checked, by structure.

    Raises:
        ValueError: naming the structure, when a layout differs. AttributeError: when the library lacks the function.
    """
    prototypes = c_prototypes((CSRC / header).read_text(encoding="utf-8"), header)
    checked = {}
    for name, struct in header_structs(header).items():
        if f"{name}_layout" not in prototypes:
            continue
        fn = getattr(lib, f"{name}_layout")
        fn.argtypes, fn.restype = [ctypes.c_void_p], ctypes.c_int64
        count = fn(None)
        values = (ctypes.c_int64 * max(count, 0))()
        fn(values)
        expected = [ctypes.sizeof(struct), *(getattr(struct, field).offset for field, _ in struct._fields_)]
        if list(values) != expected:
            raise ValueError(f"{header}: struct {name}: the compiler's layout (sizeof, offsets) {list(values)} is not "
                             f"ctypes' {expected}")
        checked[name] = expected
    return checked


class LazyLibrary:
    """A C library built on first use, once per process (thread-safe), for one caller.

    Args:
        name: library stem and the name in log messages.
        source: file name in :data:`CSRC`.
        flags: extra compiler flags (see :func:`build_library`).
        header: the header in :data:`CSRC` whose prototypes :func:`declare` sets on the loaded library (None: the
            source's stem + ``.h``). A missing symbol (``AttributeError``), or a header that cannot be read or
            parsed, makes the library unavailable.
        fallback: what the caller uses without it, for the log message.
    """

    def __init__(self, name: str, source: str, flags: Sequence[str] = (), *, header: str | None = None,
                 fallback: str) -> None:
        self.name, self.source, self.flags = name, source, tuple(flags)
        self.header = Path(source).stem + ".h" if header is None else header
        self.fallback = fallback
        self._lock = threading.Lock()
        self._built: NativeLibrary | None = None
        self._logged = False
        _DECLARED.append(self)

    def load(self) -> NativeLibrary:
        """The outcome of the build, building (and declaring the header's signatures) on the first call."""
        if self._built is None:
            with self._lock:
                if self._built is None:
                    built = build_library(self.name, self.source, self.flags)
                    self._built = self._declared(built) if built.lib is not None else built
        return self._built

    def _declared(self, built: NativeLibrary) -> NativeLibrary:
        """``built`` after declaring its signatures, or unavailable when that fails."""
        try:
            declare(built.lib, self.header)
        except AttributeError as exc:
            return NativeLibrary(None, f"the built {self.name} library lacks a symbol: {exc}")
        except (OSError, ValueError) as exc:
            return NativeLibrary(None, f"the header {self.header} of the {self.name} library is unusable: {exc}")
        return built

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
