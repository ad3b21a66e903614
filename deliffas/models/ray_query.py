"""The per-ray inputs of the light field (:class:`RayQuery`), checked once when built."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float, Integer
from torch import Tensor

from deliffas.checks import check_shape

__all__ = ["RayQuery"]


@dataclass(frozen=True)
class RayQuery:
    """N rays to shade: which frame each belongs to and where it meets the surfaces.

    Fields a variant does not read may be None (:class:`~deliffas.models.variants.VariantSpec`
    says which it reads; :meth:`DeliffasModel.shade` raises when one it needs is missing). All
    fields are tensors on the model's device.
    """

    batch_index: Integer[Tensor, "N"]
    """(N,) int64: which frame (row of the ``FrameFeatures`` batch) each ray belongs to."""
    uv_inner: Float[Tensor, "N 2"]
    """(N, 2) float32 atlas uv in [0, 1]^2 (OBJ convention, v up; unitless): inner-surface hit uv; for
    rays that miss the inner surface, the outer surface's exit (second) hit uv (see ``inner_from_outer``)."""
    uv_outer: Float[Tensor, "N 2"] | None = None
    """(N, 2) float32 atlas uv in [0, 1]^2: outer-surface first-hit uv, or None."""
    viewdir: Float[Tensor, "N 3"] | None = None
    """(N, 3) float32 unit ray directions (dimensionless), world frame, or None."""
    inner_from_outer: Bool[Tensor, "N"] | None = None
    """(N,) bool: True where ``uv_inner`` is an outer exit hit, so the inner feature is read from the
    outer map; None = all False."""

    def __post_init__(self) -> None:
        sizes = check_shape("uv_inner", self.uv_inner, "N 2")
        check_shape("batch_index", self.batch_index, "N", sizes)
        if self.uv_outer is not None:
            check_shape("uv_outer", self.uv_outer, "N 2", sizes)
        if self.viewdir is not None:
            check_shape("viewdir", self.viewdir, "N 3", sizes)
        if self.inner_from_outer is not None:
            check_shape("inner_from_outer", self.inner_from_outer, "N", sizes)
            if self.inner_from_outer.dtype != torch.bool:
                raise ValueError(f"inner_from_outer: expected dtype bool, got {self.inner_from_outer.dtype}")

    @property
    def num_rays(self) -> int:
        """N."""
        return int(self.uv_inner.shape[0])

    def __getitem__(self, index: slice) -> "RayQuery":
        """The rays ``index`` (a slice) selects, e.g. one chunk."""
        pick = lambda t: None if t is None else t[index]  # noqa: E731
        return RayQuery(self.batch_index[index], self.uv_inner[index], pick(self.uv_outer), pick(self.viewdir),
                        pick(self.inner_from_outer))

    def chunks(self, chunk_size: int):
        """Consecutive queries of at most ``chunk_size`` rays (one empty query when N = 0)."""
        if chunk_size < 1:
            raise ValueError(f"RayQuery.chunks: chunk_size must be >= 1, got {chunk_size}")
        for start in range(0, max(self.num_rays, 1), chunk_size):
            yield self[start : start + chunk_size]
