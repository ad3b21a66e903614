"""The simplest model a uv mapping allows: the mean colour of the rays that meet each texel (pure numpy).

:class:`TexelMeans` accumulates ray colours by the texel their uv falls in, at every side of a pyramid
(64 ... 1024 by default), and looks colours up at one side with holes (texels no ray met) filled from
the finest coarser side that has rays. Fitted on the training cameras' rays and scored on held-out
cameras it is an upper bound of what a static texture on that uv can explain: it has no view
direction, no pose and no shading, and its only capacity is the atlas side.
"""

from __future__ import annotations

import numpy as np

from deliffas.checks import check_shape

__all__ = ["TexelMeans", "texel_index"]


def texel_index(uv: np.ndarray, side: int) -> np.ndarray:
    """Flat row-major index of the texel each (N, 2) uv (OBJ convention, v up) falls in on a side x side atlas."""
    x = np.clip((uv[:, 0] * side).astype(np.int64), 0, side - 1)
    y = np.clip(((1.0 - uv[:, 1]) * side).astype(np.int64), 0, side - 1)
    return y * side + x


class TexelMeans:
    """Per-texel mean colour of the rays added, at each side of ``sides`` (ascending powers of two)."""

    def __init__(self, sides: tuple[int, ...] = (64, 128, 256, 512, 1024), channels: int = 3):
        if list(sides) != sorted(set(sides)) or min(sides) < 1:
            raise ValueError(f"sides must be distinct, ascending and >= 1, got {sides}")
        self.sides = tuple(sides)
        self.channels = channels
        self._sum = {s: np.zeros((s * s, channels)) for s in self.sides}
        self._count = {s: np.zeros(s * s) for s in self.sides}

    def add(self, uv: np.ndarray, colour: np.ndarray) -> None:
        """Add N rays: (N, 2) uv and their (N, C) colours."""
        sizes = check_shape("uv", uv, "N 2")
        check_shape("colour", colour, f"N {self.channels}", sizes)
        for side in self.sides:
            index = texel_index(uv, side)
            self._count[side] += np.bincount(index, minlength=side * side)
            for c in range(self.channels):
                self._sum[side][:, c] += np.bincount(index, weights=colour[:, c], minlength=side * side)

    def coverage(self, side: int) -> float:
        """Fraction of the side x side texels met by at least one ray."""
        return float((self._count[side] > 0).mean())

    def lookup(self, uv: np.ndarray, side: int) -> np.ndarray:
        """(N, C) mean colours at ``side`` for (N, 2) uv; holes from the next coarser side with rays (0 if none)."""
        if side not in self.sides:
            raise ValueError(f"side {side} is not one of {self.sides}")
        out = np.full((len(uv), self.channels), np.nan)
        for level in [s for s in self.sides if s <= side][::-1]:
            index = texel_index(uv, level)
            count = self._count[level][index]
            todo = np.isnan(out[:, 0]) & (count > 0)
            out[todo] = self._sum[level][index[todo]] / count[todo, None]
        return np.nan_to_num(out, nan=0.0)
