"""The pixels of one camera image the light field shades: what every uv rasteriser returns."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["ShadedPixels"]


@dataclass(frozen=True)
class ShadedPixels:
    """The pixels of one camera image the light field shades, in row-major order.

    The fields are numpy arrays from the CPU rasterisers (``fast.rasterize``) and torch tensors on the
    rasteriser's device from the torch rasteriser (``geometry.rasterize_torch``).

    Attributes:
        pixels: (N,) int64 flat pixel index row * W + col.
        uv_inner: (N, 2) float32, the inner surface's first-hit uv, or the outer exit uv.
        inner_from_outer: (N,) bool, True where ``uv_inner`` is the outer exit.
        uv_outer: (N, 2) float32, the outer surface's first-hit uv.
        viewdir: (N, 3) float32 unit ray directions, world frame; None when not asked for.
    """

    pixels: Any
    uv_inner: Any
    inner_from_outer: Any
    uv_outer: Any
    viewdir: Any | None

    @property
    def num_rays(self) -> int:
        """N."""
        return int(self.pixels.shape[0])
