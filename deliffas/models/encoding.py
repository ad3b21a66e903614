"""NeRF-style sinusoidal positional encoding of low-dimensional coordinates (uv, view directions).

The released DELIFFAS code imports ``Utils/positional_encoding.py``, which is missing from the
repository (dynacap-formats.md section 6), so its exact form is not established. We use the
standard NeRF embedder with the frequencies the NeRF *paper* states: for each input dimension
``x`` the features ``sin(2^k pi x)``, ``cos(2^k pi x)`` for ``k = 0 .. L-1`` (log-spaced), preceded
by the raw input. With the original's default ``multires = 10`` a uv pair gives
``2 + 2 * 2 * 10 = 42`` values, as the formats doc infers.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import nn

__all__ = ["positional_encoding", "encoded_dim", "PositionalEncoding"]

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
