"""NeRF-style sinusoidal positional encoding of low-dimensional coordinates (uv, view directions).

The released DELIFFAS code imports ``Utils/positional_encoding.py``, which is missing from the
repository (dynacap-formats.md section 6), so its exact form is not established. We use the
standard NeRF embedder with the frequencies the NeRF *paper* states: for each input dimension
``x`` the features ``sin(2^k pi x)``, ``cos(2^k pi x)`` for ``k = 0 .. L-1`` (log-spaced), preceded
by the raw input. With the original's default ``multires = 10`` a uv pair gives
``2 + 2 * 2 * 10 = 42`` values, as the formats doc infers.

:func:`encode_parts` concatenates the encodings of several coordinate sets (the MLP's input). On CPU float32
inputs that need no gradient it writes them straight into one array with a C kernel (``csrc/encoding.c``,
built on first use through :mod:`deliffas.native`), which forms the same float32 angles as
:func:`positional_encoding` and agrees with torch's sin / cos to about 1e-7; otherwise (``DELIFFAS_NATIVE=0``,
no compiler, other devices and dtypes, inputs that require grad) it is :func:`positional_encoding` and
``torch.cat``.
"""

from __future__ import annotations

import ctypes
import logging
import math
from typing import Sequence

import torch
from torch import nn

from deliffas.native import LazyLibrary

__all__ = ["positional_encoding", "encoded_dim", "encode_parts", "PositionalEncoding"]

logger = logging.getLogger(__name__)


def encoded_dim(in_dim: int, num_freqs: int, include_input: bool = True) -> int:
    """Number of output values of :func:`positional_encoding`: ``D (include_input) + 2 D L``."""
    if in_dim < 1 or num_freqs < 0:
        raise ValueError(f"encoded_dim: expected in_dim >= 1 and num_freqs >= 0, got {in_dim}, {num_freqs}")
    return in_dim * (int(include_input) + 2 * num_freqs)


def positional_encoding(x: torch.Tensor, num_freqs: int, include_input: bool = True) -> torch.Tensor:
    """Encode coordinates with sines and cosines of log-spaced frequencies ``2^k pi``.

    Layout of the last dimension (NeRF order): ``[x, sin(f_0 x), cos(f_0 x), sin(f_1 x), ...]``,
    each block holding all ``D`` input dimensions, ``f_k = 2^k pi``.

    Args:
        x: (..., D) float, e.g. uv in [0, 1]^2 or unit view directions.
        num_freqs: L >= 0, number of frequencies.
        include_input: prepend the raw coordinates.

    Returns:
        (..., D (include_input) + 2 D L), dtype and device of ``x``.
    """
    if num_freqs < 0:
        raise ValueError(f"positional_encoding: num_freqs must be >= 0, got {num_freqs}")
    if x.dim() < 1:
        raise ValueError(f"positional_encoding: x: expected shape (..., D), got {tuple(x.shape)}")
    parts = [x] if include_input else []
    if num_freqs > 0:
        freqs = math.pi * torch.pow(2.0, torch.arange(num_freqs, device=x.device, dtype=x.dtype))  # (L,)
        scaled = x.unsqueeze(-2) * freqs.unsqueeze(-1)  # (..., L, D)
        sincos = torch.stack([torch.sin(scaled), torch.cos(scaled)], dim=-2)  # (..., L, 2, D)
        parts.append(sincos.flatten(start_dim=-3))  # (..., 2 L D)
    if not parts:
        return x.new_zeros(*x.shape[:-1], 0)
    return torch.cat(parts, dim=-1)


class PositionalEncoding(nn.Module):
    """Module form of :func:`positional_encoding` for a fixed input dimension.

    Args:
        in_dim: D, size of the encoded coordinate.
        num_freqs: L, number of frequencies ``2^k pi``, k = 0 .. L-1.
        include_input: prepend the raw coordinates.
    """

    def __init__(self, in_dim: int, num_freqs: int, include_input: bool = True) -> None:
        super().__init__()
        self.in_dim = int(in_dim)
        self.num_freqs = int(num_freqs)
        self.include_input = bool(include_input)
        self.out_dim = encoded_dim(self.in_dim, self.num_freqs, self.include_input)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Encode ``x``: (..., in_dim) -> (..., out_dim)."""
        if x.shape[-1] != self.in_dim:
            raise ValueError(f"PositionalEncoding: x: expected shape (..., {self.in_dim}), got {tuple(x.shape)}")
        return positional_encoding(x, self.num_freqs, self.include_input)

    def extra_repr(self) -> str:
        return f"in_dim={self.in_dim}, num_freqs={self.num_freqs}, include_input={self.include_input}, out_dim={self.out_dim}"


_MAX_FREQS, _MAX_DIMS = 16, 4
"""The most frequencies and coordinates per part the kernel encodes (``csrc/encoding.c``); more take the torch path."""


_KERNEL = LazyLibrary("encoding", "encoding.c", ("-fno-fast-math", "-ffp-contract=off", "-fno-math-errno",
                                                  "-fno-trapping-math"),
                      fallback="torch sin / cos for the positional encodings, slower")  # signatures: encoding.h


def _encode_native(parts: Sequence[tuple[torch.Tensor, PositionalEncoding]]) -> torch.Tensor | None:
    """The kernel's concatenated encodings (..., E), or None where it does not apply or is not built."""
    grad = torch.is_grad_enabled()
    if any(x.device.type != "cpu" or x.dtype != torch.float32 or (grad and x.requires_grad)
           or pe.num_freqs > _MAX_FREQS or pe.in_dim > _MAX_DIMS for x, pe in parts):
        return None
    lead = parts[0][0].shape[:-1]
    if any(x.shape[:-1] != lead for x, _ in parts):
        return None  # the torch path raises torch.cat's error
    lib = _KERNEL.get()
    if lib is None:
        return None
    xs = [x.contiguous() for x, _ in parts]
    n, width = xs[0][..., 0].numel(), sum(pe.out_dim for _, pe in parts)
    out = torch.empty(*lead, width, dtype=torch.float32)
    count = len(parts)
    ptrs = (ctypes.c_void_p * count)(*[x.data_ptr() for x in xs])
    dims = (ctypes.c_int32 * count)(*[pe.in_dim for _, pe in parts])
    freqs = (ctypes.c_int32 * count)(*[pe.num_freqs for _, pe in parts])
    include = (ctypes.c_int32 * count)(*[int(pe.include_input) for _, pe in parts])
    # ctypes releases the GIL for the call; xs and out are referenced until it returns
    if lib.deliffas_encode_parts_f32(count, ptrs, dims, freqs, include, n, out.data_ptr(), width):
        return None  # a coordinate beyond the kernel's range: torch encodes it
    return out


def encode_parts(parts: Sequence[tuple[torch.Tensor, PositionalEncoding]]) -> torch.Tensor:
    """The concatenation of several encodings: ``torch.cat([pe(x) for x, pe in parts], dim=-1)``.

    Args:
        parts: (x, pe) pairs, x (..., pe.in_dim) with the same leading shape in every pair.

    Returns:
        (..., sum of pe.out_dim), dtype and device of the inputs. On CPU float32 inputs that need no
        gradient (none requires grad, or grad mode is off) it comes from the C kernel (see the module
        docstring), else from torch.
    """
    if not parts:
        raise ValueError("encode_parts: expected at least one (x, encoding) pair, got none")
    for x, pe in parts:
        if x.dim() < 1 or x.shape[-1] != pe.in_dim:
            raise ValueError(f"encode_parts: x: expected shape (..., {pe.in_dim}), got {tuple(x.shape)}")
    out = _encode_native(parts)
    if out is not None:
        return out
    encoded = [pe(x) for x, pe in parts]
    return encoded[0] if len(encoded) == 1 else torch.cat(encoded, dim=-1)
