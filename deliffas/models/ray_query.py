"""The per-ray inputs of the light field (:class:`RayQuery`), checked once when built, and the way to them.

The one way from rays to the model and back: :func:`stack_rays` flattens camera ray sets
(``geometry.camera_rays.CameraRays``) into a :class:`RayBatch`, :func:`ray_query` turns the batch into the
model's :class:`RayQuery` for a variant's spec, and :func:`paint_images` writes the shaded colours into images
(train, evaluate, render and the fast path use them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import torch
from jaxtyping import Bool, Float, Integer
from torch import Tensor

from deliffas.checks import check_shape

if TYPE_CHECKING:
    from deliffas.geometry.camera_rays import CameraRays
    from deliffas.models.variants import VariantSpec

__all__ = ["RayQuery", "RayBatch", "stack_rays", "ray_query", "paint_images"]


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


@dataclass(frozen=True)
class RayBatch:
    """The rays of several cameras (and frames) flattened for one ``DeliffasModel.shade`` call.

    Attributes:
        batch_index: (N,) long, the frame (row of the FrameFeatures batch) of each ray.
        image_index: (N,) long, the image (frame, camera) of each ray, into the stacked images.
        pixels: (N,) long flat pixel index in its image.
        uv_inner, uv_outer: (N, 2) float.
        inner_from_outer: (N,) bool.
        viewdir: (N, 3) float (None from the fast path for variants without a view direction).
    """

    batch_index: torch.Tensor
    image_index: torch.Tensor
    pixels: torch.Tensor
    uv_inner: torch.Tensor
    uv_outer: torch.Tensor
    inner_from_outer: torch.Tensor
    viewdir: torch.Tensor | None

    def to(self, device: torch.device | str) -> "RayBatch":
        return RayBatch(*(getattr(self, f).to(device) for f in self.__dataclass_fields__))

    @property
    def num_rays(self) -> int:
        return int(self.pixels.shape[0])


def stack_rays(rays: Sequence["CameraRays"], frame_of_image: Sequence[int]) -> RayBatch:
    """Flatten per-image ray sets; ``frame_of_image[i]`` is the feature batch row of image i."""
    counts = [r.num_rays for r in rays]
    cat = lambda name: torch.cat([torch.as_tensor(getattr(r, name)) for r in rays])  # noqa: E731
    pixels = cat("pixels")
    dev = pixels.device  # the rays' device: the torch rasteriser's rays stay where they were made
    per_image = torch.as_tensor(counts, device=dev)
    return RayBatch(
        batch_index=torch.repeat_interleave(torch.as_tensor(list(frame_of_image), dtype=torch.long, device=dev),
                                            per_image),
        image_index=torch.repeat_interleave(torch.arange(len(rays), device=dev), per_image),
        pixels=pixels,
        uv_inner=cat("uv_inner"),
        uv_outer=cat("uv_outer"),
        inner_from_outer=cat("inner_from_outer"),
        viewdir=cat("viewdir"),
    )


def ray_query(batch: RayBatch, spec: "VariantSpec") -> RayQuery:
    """The model's inputs for ``batch``: the per-ray fields ``spec`` reads, None for the others."""
    return RayQuery(
        batch_index=batch.batch_index,
        uv_inner=batch.uv_inner,
        uv_outer=batch.uv_outer if spec.uses_uv_outer else None,
        viewdir=batch.viewdir if spec.viewdir else None,
        inner_from_outer=batch.inner_from_outer if spec.inner_from_outer else None,
    )


def paint_images(colors: torch.Tensor, batch: RayBatch, num_images: int, height: int, width: int,
                 background: float = 0.0) -> torch.Tensor:
    """Images (num_images, H, W, 3) with each ray's colour at its pixel and ``background`` elsewhere.

    Args:
        colors: (N, 3) shaded colours of ``batch``'s rays (differentiable: the result is built
            out of place, so gradients reach ``colors``).
        batch: the rays (their ``image_index`` and flat ``pixels``).
        num_images: number of images of the canvas.
        height: the canvas height, pixels.
        width: the canvas width, pixels.
        background: value of the pixels no ray paints.
    """
    check_shape("colors", colors, f"{batch.num_rays} 3")
    canvas = colors.new_full((num_images, height * width, 3), background)
    canvas = canvas.index_put((batch.image_index, batch.pixels), colors)
    return canvas.reshape(num_images, height, width, 3)
