"""Shape and value checks run once at public API boundaries (never in inner loops)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["check_shape", "check_finite", "finite_as"]


def _shape_of(x: Any) -> tuple[int, ...]:
    return tuple(int(s) for s in x.shape)


def check_shape(name: str, x: Any, spec: str, sizes: dict[str, int] | None = None) -> dict[str, int]:
    """Check that array/tensor ``x`` matches ``spec`` and return the bound letter sizes.

    Args:
        name: what ``x`` is called in the caller's API (used in the message).
        x: numpy array or torch tensor.
        spec: space-separated dimensions, letters bind a size (``"B V 3"``), digits must match,
            ``*`` matches any number of leading dimensions, ``_`` one dimension of any size.
        sizes: already bound letters (e.g. ``{"V": 5514}``); updated copy is returned.

    Raises:
        ValueError: naming ``name``, the expected spec and the actual shape (never the values).
    """
    bound = dict(sizes or {})
    shape = _shape_of(x)
    dims = spec.split()
    if dims and dims[0] == "*":
        dims = dims[1:]
        if len(shape) < len(dims):
            raise ValueError(f"{name}: expected shape (..., {', '.join(dims)}), got {shape}")
        shape = shape[len(shape) - len(dims):]
    elif len(shape) != len(dims):
        raise ValueError(f"{name}: expected shape ({', '.join(dims)}), got {_shape_of(x)}")
    for d, s in zip(dims, shape):
        if d == "_":
            continue
        if d.isdigit():
            if int(d) != s:
                raise ValueError(f"{name}: expected shape ({', '.join(dims)}), got {_shape_of(x)}")
        elif d in bound and bound[d] != s:
            raise ValueError(f"{name}: dimension {d} should be {bound[d]}, got shape {_shape_of(x)}")
        else:
            bound[d] = s
    return bound


def check_finite(name: str, x: Any) -> None:
    """Raise ValueError when ``x`` holds NaN or inf (reports how many, not the values)."""
    try:
        import torch

        if isinstance(x, torch.Tensor):
            bad = int((~torch.isfinite(x)).sum())
        else:
            bad = int((~np.isfinite(np.asarray(x))).sum())
    except ImportError:  # pragma: no cover - torch is a hard dependency
        bad = int((~np.isfinite(np.asarray(x))).sum())
    if bad:
        raise ValueError(f"{name}: {bad} non-finite values (NaN or inf) in array of shape {_shape_of(x)}")


def finite_as(name: str, x: Any, dtype: Any) -> np.ndarray:
    """``x`` as a numpy array of ``dtype``, refused when it holds NaN or inf in that dtype: what a writer stores
    must read back as numbers (1e307 is finite in float64 and inf in a float32 PLY).

    Raises:
        ValueError: ``<name>: N of M values are not finite as <dtype> (NaN, inf or beyond its range); not written``.
    """
    with np.errstate(over="ignore", invalid="ignore"):  # an overflowing cast gives inf, refused below
        a = np.asarray(x).astype(dtype, copy=False)
    if a.dtype.kind in "fc":
        bad = int((~np.isfinite(a)).sum())
        if bad:
            raise ValueError(f"{name}: {bad} of {a.size} values are not finite as {np.dtype(dtype).name} "
                             "(NaN, inf or beyond its range); not written")
    return a
