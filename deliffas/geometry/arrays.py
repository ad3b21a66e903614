"""The array policy of the geometry API, and its one converter.

A public geometry function that takes arrays and returns arrays returns the kind it was given:
numpy in -> numpy out, torch in -> torch out on the input's device and in its floating dtype
(docs/conventions.md, "Arrays"). Functions compute in whichever library suits them (torch for
batched maths, numpy float64 with scipy/open3d for mesh processing); they convert at their entry
with :func:`to_torch` / :func:`to_numpy` and give the result back in the caller's kind with
:func:`like`. Torch-only functions (modules, differentiable maths) and numpy records say so in
their docstrings.

``ArrayLike`` is the type of an argument that may be either; the shape annotations use it as
``Float[ArrayLike, "V 3"]`` (jaxtyping checks each member of the union).
"""

from __future__ import annotations

from typing import Union

import numpy as np
import torch

__all__ = ["ArrayLike", "to_torch", "to_numpy", "like", "is_numpy", "require_tensor"]

ArrayLike = Union[np.ndarray, torch.Tensor]
"""A numpy array or a torch tensor."""


def is_numpy(x: object) -> bool:
    """True for anything that is not a torch tensor (numpy arrays, lists, scalars)."""
    return not isinstance(x, torch.Tensor)


def to_torch(x: object, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> torch.Tensor:
    """``x`` as a tensor (0-d for a scalar); a writable numpy array shares its memory when no dtype
    or device change is asked (read-only or negatively strided ones are copied: torch needs neither)."""
    if isinstance(x, torch.Tensor):
        t = x
    else:
        a = np.asarray(x)
        if not a.flags.writeable or any(s < 0 for s in a.strides):
            a = a.copy()
        t = torch.from_numpy(a)
    return t if dtype is None and device is None else t.to(device=device, dtype=dtype)


def to_numpy(x: object, dtype: np.dtype | type | None = None) -> np.ndarray:
    """``x`` as a numpy array (a tensor is detached and copied to the CPU)."""
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    return a if dtype is None else a.astype(dtype, copy=False)


def require_tensor(name: str, x: object, boundary: str) -> None:
    """The entry check of a torch-only function: TypeError naming ``name`` and where numpy is taken."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__} (torch-only; {boundary})")


def like(out: object, ref: object) -> ArrayLike:
    """``out`` in the kind of ``ref``: numpy for a numpy ``ref``, a tensor on ``ref``'s device for a
    tensor ``ref``. A floating ``out`` takes ``ref``'s dtype when ``ref`` is floating too (so float32
    vertices give float32 results even where the work ran in float64); other dtypes are kept."""
    if isinstance(ref, torch.Tensor):
        t = to_torch(out)
        dtype = ref.dtype if t.is_floating_point() and ref.is_floating_point() else None
        return t.to(device=ref.device, dtype=dtype)
    a = to_numpy(out)
    ref_dtype = np.asarray(ref).dtype
    if a.dtype.kind == "f" and ref_dtype.kind == "f":
        return a.astype(ref_dtype, copy=False)
    return a
