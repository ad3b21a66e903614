"""Unpickling the numpy data of dataset files (ZJU-MoCap ``.npy`` dicts, SMPL ``.pkl`` models) without trusting them.

A pickle names the functions it calls and the states it sets; an allow-list of classes alone is not
enough for numpy: a damaged dtype state (its ``flags`` or item size, set by the BUILD opcode) made
numpy lose track of object references, and the process crashed a few files later (found by fuzzing:
"deallocated bytearray object has exported buffers", then SIGSEGV in ``OBJECT_legacy_setitem``). So
this unpickler (Python's pure-Python ``pickle._Unpickler``, whose opcodes can be overridden) builds
numpy values only from checked arguments:

- ``numpy.dtype(name, ...)``: a plain dtype of a known kind from its name; the pickled state
  (flags, item size, alignment) is ignored except for the byte order.
- ``numpy.ndarray`` states ``(version, shape, dtype, fortran, data)``: non-negative shape, ``data``
  a list of exactly that many objects for object arrays, else bytes of exactly that many items.
- ``_frombuffer`` and ``scalar``: bytes of the right length, never object dtypes.
- ``copyreg._reconstructor``: only for the classes the caller allows (scipy sparse matrices for SMPL).

Anything else (another class, a refused argument, a truncated or damaged stream) raises
``UnsafePickleError`` (a ValueError).
"""

from __future__ import annotations

import io
import pickle
from typing import Any, Callable

import numpy as np

__all__ = ["UnsafePickleError", "load_numpy_pickle"]


class UnsafePickleError(ValueError):
    """A pickle that is damaged or asks for something outside the numpy subset."""


class _ArrayClass:
    """Stands for ``numpy.ndarray`` in the stream: only ``_reconstruct`` accepts it (no NEWOBJ/REDUCE on the class)."""

    def __call__(self, *args, **kwargs):
        raise UnsafePickleError("refusing to call numpy.ndarray from a pickle")


_ARRAY = _ArrayClass()
_KINDS = "biufcOSU"


def _dtype(name, align=False, copy=True) -> np.dtype:
    if not isinstance(name, str) or len(name) > 8:
        raise UnsafePickleError(f"refusing dtype {name!r}")
    dt = np.dtype(name)
    if dt.kind not in _KINDS or dt.fields is not None or dt.subdtype is not None:
        raise UnsafePickleError(f"refusing dtype {name!r}")
    return dt


def _reconstruct(subtype, shape, dtype) -> np.ndarray:
    if subtype is not _ARRAY:
        raise UnsafePickleError("refusing _reconstruct of anything but numpy.ndarray")
    return np.ndarray((0,), np.uint8)  # an empty array; its BUILD state is checked by _set_array_state


def _count(shape) -> int:
    if not (isinstance(shape, tuple) and all(isinstance(s, int) and 0 <= s < 2**40 for s in shape) and len(shape) <= 32):
        raise UnsafePickleError(f"refusing array shape {shape!r}"[:120])
    n = 1
    for s in shape:
        n *= s
    return n


def _frombuffer(buf, dtype, shape, order) -> np.ndarray:
    if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(buf, (bytes, bytearray)) or order not in "CF":
        raise UnsafePickleError("refusing _frombuffer arguments")
    if len(buf) != _count(shape) * dtype.itemsize:
        raise UnsafePickleError(f"array data of {len(buf)} bytes for shape {shape} of {dtype}")
    return np.frombuffer(bytes(buf), dtype).reshape(shape, order=order).copy()


def _scalar(dtype, data=None):
    if not isinstance(dtype, np.dtype):
        raise UnsafePickleError("refusing a scalar without a dtype")
    if dtype.hasobject:
        return data
    if not isinstance(data, bytes) or len(data) != dtype.itemsize:
        raise UnsafePickleError(f"refusing a {dtype} scalar of {len(data) if isinstance(data, bytes) else '?'} bytes")
    return np.frombuffer(data, dtype)[0]


def _bytes(*args):
    """``bytes()`` and ``bytes(b)``: how protocol 2 writes empty and some other bytes objects."""
    if args == ():
        return b""
    if len(args) == 1 and isinstance(args[0], bytes):
        return args[0]
    raise UnsafePickleError("refusing bytes() arguments")


def _encode(obj, encoding="utf-8"):
    if not isinstance(obj, str) or encoding not in ("latin1", "latin-1"):
        raise UnsafePickleError("refusing _codecs.encode arguments")
    return obj.encode("latin1")


def _set_array_state(arr: np.ndarray, state) -> None:
    if not (isinstance(state, tuple) and len(state) in (4, 5)):
        raise UnsafePickleError("refusing an array state")
    shape, dtype, fortran, data = state[-4:]
    if not isinstance(dtype, np.dtype) or not isinstance(fortran, bool):
        raise UnsafePickleError("refusing an array state")
    n = _count(shape)
    if dtype.hasobject:
        if not (isinstance(data, list) and len(data) == n):
            raise UnsafePickleError(f"object array data must be a list of {n} items")
    elif not (isinstance(data, bytes) and len(data) == n * dtype.itemsize):
        raise UnsafePickleError(f"array data of shape {shape} and {dtype} must be {n * dtype.itemsize} bytes")
    arr.__setstate__((1, shape, dtype, fortran, data))


class _NumpyUnpickler(pickle._Unpickler):
    """``pickle._Unpickler`` whose globals and BUILD go through the checks above."""

    dispatch = dict(pickle._Unpickler.dispatch)

    def __init__(self, data: bytes, extra: Callable[[str, str], type | str | None] | None):
        super().__init__(io.BytesIO(data), encoding="latin1")
        self.extra = extra
        self.classes: set[type] = set()  # the caller's classes met so far

    def find_class(self, module: str, name: str):
        if (module, name) in _NUMPY:
            return _NUMPY[(module, name)]
        if (module, name) in (("copy_reg", "_reconstructor"), ("copyreg", "_reconstructor")):
            return self._reconstructor
        if (module, name) in (("__builtin__", "object"), ("builtins", "object")):
            return object
        found = self.extra(module, name) if self.extra is not None else None
        if isinstance(found, type):
            self.classes.add(found)
            return found
        raise UnsafePickleError(found or f"refusing to load '{module}.{name}' from a pickle; only numpy arrays are allowed")

    def _reconstructor(self, cls, base, state):
        if cls not in self.classes or base is not object or state is not None:
            raise UnsafePickleError(f"refusing copyreg._reconstructor({getattr(cls, '__name__', cls)!r}, ...)")
        return object.__new__(cls)

    def load_build(self):
        state = self.stack.pop()
        inst = self.stack[-1]
        if isinstance(inst, np.ndarray):
            _set_array_state(inst, state)
        elif isinstance(inst, np.dtype):  # only the byte order of a pickled dtype state is used
            order = state[1] if isinstance(state, tuple) and len(state) > 1 else "|"
            if order in ("<", ">") and inst.byteorder != "|" and inst != inst.newbyteorder(order):
                swapped = inst.newbyteorder(order)
                self.stack[-1] = swapped
                for k, v in self.memo.items():  # later references to the dtype come from the memo
                    if v is inst:
                        self.memo[k] = swapped
        elif type(inst) in self.classes and isinstance(state, dict):
            inst.__dict__.update(state)
        else:
            raise UnsafePickleError(f"refusing to set the state of a {type(inst).__name__}")

    dispatch[pickle.BUILD[0]] = load_build


_NUMPY: dict[tuple[str, str], Any] = {("numpy", "ndarray"): _ARRAY, ("numpy", "dtype"): _dtype, ("_codecs", "encode"): _encode,
                                      ("__builtin__", "bytes"): _bytes, ("builtins", "bytes"): _bytes}
for _core in ("numpy.core", "numpy._core"):
    _NUMPY[(f"{_core}.multiarray", "_reconstruct")] = _reconstruct
    _NUMPY[(f"{_core}.multiarray", "scalar")] = _scalar
    _NUMPY[(f"{_core}.numeric", "_frombuffer")] = _frombuffer


def load_numpy_pickle(data: bytes, extra: Callable[[str, str], type | str | None] | None = None) -> Any:
    """Unpickle ``data`` allowing numpy arrays, dtypes and scalars and Python's plain containers.

    Args:
        extra: called with (module, name) of any other global: a class to allow (rebuilt with
            ``object.__new__`` and its ``__dict__`` set from the stream; the caller checks the result),
            a message to refuse it with, or None for the default refusal.

    Raises:
        UnsafePickleError: a refused global or argument, or a damaged stream.
    """
    try:
        return _NumpyUnpickler(data, extra).load()
    except UnsafePickleError:
        raise
    except Exception as err:  # a damaged stream fails in many ways (EOFError, KeyError of the memo, ...)
        raise UnsafePickleError(f"damaged pickle ({type(err).__name__}: {str(err)[:200]})") from None
