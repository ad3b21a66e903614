"""Hypothesis strategies that turn one valid file into a broken one, shared by the fuzz tests.

- ``bytes_cases(valid)``: any file — truncation, bit flips, spliced bytes, a huge integer written over
  a count, random bytes.
- ``text_cases(valid, sep)``: a text file — lines dropped, repeated or shuffled, a token replaced by a
  nasty one (NaN, inf, huge, empty, another type), other encodings and line ends, a NUL byte.
- ``tree_cases(tree, kind)``: a parsed file (``"json"``: JSON values; ``"numpy"``: dicts and lists of
  numpy arrays, as in an ``.npz``, a pickled ``.npy`` dict or an HDF5 tree) — one edit anywhere: a value
  replaced by a nasty one (NaN/inf, huge, other dtype or type, wrong shape, fewer or more rows, empty),
  a key dropped or renamed, a list entry dropped or repeated, a value wrapped in a list.

The readers under test must end each case with valid data or their own error naming the file.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
from hypothesis import strategies as st

__all__ = ["bytes_cases", "text_cases", "tree_cases", "NASTY_TOKENS"]

NASTY_TOKENS = ["nan", "NaN", ".nan", "inf", "-inf", ".Inf", "1e999", "-1e999", "1e308", "", "x", "0x1F", "1" * 400,
                "-1", "0", "99999999999999999999", "1.5.5", "１２", "\t", "\x00", "é", "null", "[", "]", "{", ",",
                "1e-999", "-0", "\"", "'", ":", "#", "!!opencv-matrix", "4294967295", "-2147483649"]
"""Tokens written in place of a valid one."""


def _flip(valid: bytes, positions: list[tuple[int, int]]) -> bytes:
    data = bytearray(valid)
    for pos, bit in positions:
        data[pos % len(data)] ^= 1 << bit
    return bytes(data)


def _overwrite(valid: bytes, pos: int, value: bytes) -> bytes:
    pos = pos % max(len(valid), 1)
    return valid[:pos] + value + valid[pos + len(value):]


_HUGE = [(2**64 - 1).to_bytes(8, "little"), (2**63).to_bytes(8, "little"), (2**31).to_bytes(4, "little"),
         (2**32 - 1).to_bytes(4, "little"), (10**6).to_bytes(8, "little"), b"\x00" * 8, b"\xff" * 4]


def bytes_cases(valid: bytes):
    """Byte-level damage of ``valid``: truncated, 1-4 bits flipped, bytes spliced in, a count overwritten
    with a huge or zero integer, or random bytes."""
    n = len(valid)
    return st.one_of(
        st.integers(0, max(n - 1, 0)).map(lambda k: valid[:k]),
        st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 7)), min_size=1, max_size=4)
        .map(lambda p: _flip(valid, p)),
        st.tuples(st.integers(0, n), st.binary(max_size=64)).map(lambda t: valid[:t[0]] + t[1] + valid[t[0]:]),
        st.tuples(st.integers(0, max(n - 1, 0)), st.sampled_from(_HUGE)).map(lambda t: _overwrite(valid, *t)),
        st.binary(max_size=256))


@st.composite
def text_cases(draw, valid: bytes, sep: bytes = b" "):
    """Line and token damage of the text file ``valid`` whose tokens are separated by ``sep``."""
    lines = valid.split(b"\n")
    kind = draw(st.sampled_from(["token", "swap_tokens", "drop_token", "drop_line", "dup_line", "shuffle",
                                 "encoding", "newlines", "nul"]))
    if kind in ("token", "swap_tokens", "drop_token"):
        i = draw(st.integers(0, len(lines) - 1))
        toks = lines[i].split(sep)
        j = draw(st.integers(0, max(len(toks) - 1, 0)))
        if kind == "token":
            toks[j] = draw(st.sampled_from(NASTY_TOKENS)).encode("utf-8")
        elif kind == "drop_token":
            del toks[j]
        else:
            k = draw(st.integers(0, max(len(toks) - 1, 0)))
            toks[j], toks[k] = toks[k], toks[j]
        lines[i] = sep.join(toks)
        return b"\n".join(lines)
    if kind == "drop_line":
        i = draw(st.integers(0, len(lines) - 1))
        return b"\n".join(lines[:i] + lines[i + 1:])
    if kind == "dup_line":
        i = draw(st.integers(0, len(lines) - 1))
        return b"\n".join(lines[:i] + [lines[i]] * draw(st.integers(2, 20)) + lines[i:])
    if kind == "shuffle":
        perm = draw(st.permutations(range(len(lines))))
        return b"\n".join(lines[i] for i in perm)
    if kind == "encoding":
        return valid.decode("utf-8").encode(draw(st.sampled_from(["utf-16", "utf-32", "utf-8-sig"])))
    if kind == "newlines":
        seps = draw(st.lists(st.sampled_from([b"\n", b"\r\n", b"\r", b"\n\n"]), min_size=len(lines), max_size=len(lines)))
        return b"".join(ln + s for ln, s in zip(lines, seps))
    pos = draw(st.integers(0, len(valid)))
    return valid[:pos] + b"\x00" + valid[pos:]


# ------------------------------------------------------------------------------------------ trees
def _paths(tree: Any, prefix: tuple = ()) -> list[tuple]:
    """Every node of ``tree`` (dicts and lists are walked; arrays and scalars are leaves), root first."""
    out = [prefix]
    if isinstance(tree, dict):
        for k, v in tree.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            out += _paths(v, prefix + (i,))
    return out


def _get(tree: Any, path: tuple) -> Any:
    for k in path:
        tree = tree[k]
    return tree


def _json_nasty(value: Any) -> list:
    """JSON values to put where ``value`` was."""
    out = [math.nan, math.inf, -math.inf, 1e308, -1e308, 10**400, -(10**400), 2**63, -1, 0, 0.5, "", "x", "1",
           None, True, [], {}, [[]], [math.nan] * 3, [0] * 9, [[1, 0, 0], [0, 1, 0]], [[1, 2], [3]], {"a": 1}]
    if isinstance(value, list) and value:
        out += [value[:-1], value + [value[-1]], [value], value[0],
                [v[:-1] if isinstance(v, list) and v else v for v in value],
                [[x * 2 for x in v] if isinstance(v, list) and all(isinstance(x, (int, float)) for x in v) else v
                 for v in value]]
        flat = np.ravel(np.array(value, dtype=object)).tolist() if _rectangular(value) else None
        if flat is not None:
            out += [flat, [-x if isinstance(x, (int, float)) else x for x in flat]]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        out += [value * 1e300, -value, value + 0.5, str(value), [value]]
    return out


def _rectangular(value: list) -> bool:
    try:
        np.array(value, dtype=np.float64)
        return True
    except (TypeError, ValueError, OverflowError):
        return False


def _numpy_nasty(value: Any) -> list:
    """Makers of numpy values (and a few Python ones) to put where ``value`` was (built only when drawn:
    some arrays are large)."""
    out: list = [lambda: np.float64(np.nan), lambda: np.array([]), lambda: np.array("x"), lambda: np.array(b"\xff"),
                 lambda: np.zeros((0, 3)), lambda: np.zeros((2, 2, 2, 2)), lambda: None, lambda: "x", lambda: 1.0,
                 lambda: [1, 2], lambda: {"a": np.zeros(3)}, lambda: np.array([np.inf, 1.0])]
    if isinstance(value, np.ndarray):
        a = value
        if a.dtype.kind in "fiub" and a.size:
            f = lambda: a.astype(np.float64)  # noqa: E731
            out += [lambda: _set_flat(f(), len(a.flat) // 2, np.nan), lambda: _set_flat(f(), 0, -np.inf),
                    lambda: f() * 1e308 + 1e308, lambda: -f(), lambda: a.astype(np.float16),
                    lambda: a.astype(np.complex128), lambda: a.astype(np.int32), lambda: a.astype(np.uint8),
                    lambda: a.astype(bool), lambda: a.astype("U8"), lambda: a.astype("S8")]
        out += [lambda: a.reshape(-1), lambda: a[..., None], lambda: a.T, lambda: np.array(a, dtype=object)]
        if a.ndim:  # fewer or more rows or columns, none at all, one value
            out += [lambda: a[:1], lambda: a[:-1], lambda: a[1:], lambda: np.concatenate([a, a]), lambda: a[..., :-1],
                    lambda: np.tile(a, 2), lambda: np.zeros((0,) + a.shape[1:], a.dtype),
                    lambda: np.array(a.flat[0]) if a.size else a]
        if a.dtype == np.uint8 and a.ndim == 1 and a.size > 8:  # an encoded image: damage its bytes
            out += [lambda: a[: a.size // 2], lambda: _flip_array(a, 0.01), lambda: _flip_array(a, 0.2),
                    lambda: a[::-1].copy(), lambda: np.concatenate([a[:20], a[40:]])]
    if isinstance(value, (list, tuple)) and value:
        out += [lambda: list(value)[:-1], lambda: list(value) + [value[-1]], lambda: value[0], lambda: tuple(value),
                lambda: set(range(len(value)))]
    if isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
        out += [lambda: -value, lambda: value * 1e300, lambda: np.float64(np.inf), lambda: str(value)]
    return out


def _set_flat(a: np.ndarray, i: int, v: float) -> np.ndarray:
    a.flat[i] = v
    return a


def _flip_array(a: np.ndarray, fraction: float) -> np.ndarray:
    out = a.copy()
    idx = np.random.default_rng(a.size).choice(a.size, max(1, int(fraction * a.size)), replace=False)
    out[idx] ^= np.uint8(0x5A)
    return out


def _copy_containers(tree: Any) -> Any:
    """A copy of the dicts and lists of ``tree`` sharing its leaves (arrays are never edited in place)."""
    if isinstance(tree, dict):
        return {k: _copy_containers(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_copy_containers(v) for v in tree]
    return tree


@st.composite
def tree_cases(draw, tree: Any, kind: str = "json"):
    """``tree`` (not modified) with one structural edit; ``kind`` "json" or "numpy" chooses the nasty values."""
    tree = _copy_containers(tree)
    paths = _paths(tree)
    path = draw(st.sampled_from(paths))
    op = draw(st.sampled_from(["replace", "replace", "replace", "drop", "rename", "dup", "wrap"]))
    value = _get(tree, path)
    if op == "replace" or not path:
        if kind == "json":
            new = copy.deepcopy(draw(st.sampled_from(_json_nasty(value))))
        else:
            new = draw(st.sampled_from(_numpy_nasty(value)))()
    elif op == "wrap":
        new = [value]
    else:
        parent, key = _get(tree, path[:-1]), path[-1]
        if op == "drop":
            del parent[key]
        elif op == "rename" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["", "x", "0", "names", "K", "frames"]))] = parent.pop(key)
        elif op == "dup" and isinstance(parent, list):
            parent.insert(key, _copy_containers(value))
        else:
            parent[key] = None
        return tree
    if not path:
        return new
    _get(tree, path[:-1])[path[-1]] = new
    return tree
