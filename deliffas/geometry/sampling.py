"""Bilinear lookup of atlas-space maps at uv coordinates: the project's one uv sampler.

Convention (docs/conventions.md): texel (row i, col j) of an S x S atlas image has its centre at
``u = (j + 0.5) / S``, ``v = 1 - (i + 0.5) / S`` (row 0 is the top, v = 1). The lookup is
``torch.nn.functional.grid_sample(..., mode="bilinear", align_corners=False,
padding_mode="border")`` with grid ``x = 2u - 1``, ``y = 2(1 - v) - 1``, which is exactly consistent
with those texel centres. Queries outside the outermost texel centres take the border value.

Training samples through a gather of the 4 corner texels and a scatter-add backward
(``_GatherBilinear``); on CPU float32 both run as one C loop each (``csrc/gather_bilinear.c``, built
on first use through :mod:`deliffas.native`), else as torch ``index_select`` / ``index_add_``
(``DELIFFAS_NATIVE=0``, no compiler, other devices and dtypes). Both give the same values up to the
order of float additions.

Note the original DELIFFAS code sampled at (row, col) = ((1 - v) S, u S) with integer coordinates
at texel centres (a half-texel shift against its rasterised texels, formats doc pitfall 12); we
use the centred convention above everywhere instead.
"""

from __future__ import annotations

import ctypes
import logging

import torch
import torch.nn.functional as F
from jaxtyping import Float, Integer
from torch import Tensor

from deliffas.checks import check_shape
from deliffas.geometry.arrays import require_tensor
from deliffas.native import LazyLibrary

__all__ = ["sample_uv", "uv_to_grid"]

logger = logging.getLogger(__name__)


def uv_to_grid(uv: Float[Tensor, "*N 2"]) -> Float[Tensor, "*N 2"]:
    """Map uv in [0, 1]^2 (OBJ convention, v up) to grid_sample coordinates in [-1, 1]^2.

    Args:
        uv: (..., 2) float.

    Returns:
        (..., 2): ``x = 2u - 1``, ``y = 2(1 - v) - 1 = 1 - 2v``.
    """
    return torch.stack([2.0 * uv[..., 0] - 1.0, 1.0 - 2.0 * uv[..., 1]], dim=-1)


def bilinear_corners(uv: Float[Tensor, "M 2"], height: int, width: int
                     ) -> tuple[Integer[Tensor, "4 M"], Float[Tensor, "4 M"]]:
    """The 4 texels (flat row-major indices) and bilinear weights of each uv on an H x W map.

    Exactly ``grid_sample(mode="bilinear", padding_mode="border", align_corners=False)``'s lookup:
    the texel coordinate ``x = u W - 0.5``, ``y = (1 - v) H - 0.5`` is clamped to the outermost texel
    centres, corners ``(x0, y0), (x1, y0), (x0, y1), (x1, y1)``, weights summing to 1.
    """
    x = (uv[:, 0] * width - 0.5).clamp(0, width - 1)
    y = ((1.0 - uv[:, 1]) * height - 0.5).clamp(0, height - 1)
    x0f, y0f = x.floor(), y.floor()
    wx, wy = x - x0f, y - y0f
    x0, y0 = x0f.long(), y0f.long()
    x1, y1 = (x0 + 1).clamp(max=width - 1), (y0 + 1).clamp(max=height - 1)
    index = torch.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1])
    weight = torch.stack([(1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy])
    return index, weight


_KERNEL = LazyLibrary("gather_bilinear", "gather_bilinear.c",  # signatures: gather_bilinear.h
                      fallback="torch index_select / index_add_ for the bilinear gather, slower")


def _native(values: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> ctypes.CDLL | None:
    """The C kernel when it applies (CPU, float32 values and weights, int64 indices) and is built, else None."""
    if values.device.type != "cpu" or values.dtype != torch.float32 or weight.dtype != torch.float32:
        return None
    if index.dtype != torch.int64 or index.device.type != "cpu" or weight.device.type != "cpu":
        return None
    return _KERNEL.get()


class _GatherBilinear(torch.autograd.Function):
    """Bilinear lookup of a channels-last (1, C, H, W) map at fixed corners: a gather forward and a
    scatter-add backward (the C kernel, else ``index_add_``), several times faster on CPU than
    ``grid_sample``'s backward. The uv get no gradient (use ``grid_sample`` when they need one)."""

    @staticmethod
    def forward(ctx, feature_map: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        _, channels, height, width = feature_map.shape
        flat = feature_map.permute(0, 2, 3, 1).reshape(-1, channels)  # (H W, C), a view
        ctx.save_for_backward(index, weight)
        ctx.map_shape = feature_map.shape
        lib = _native(flat, index, weight)
        if lib is not None:
            flat, index, weight = flat.contiguous(), index.contiguous(), weight.contiguous()
            out = flat.new_empty(index.shape[1], channels)
            # ctypes releases the GIL for the call; every tensor is referenced until it returns
            if not lib.deliffas_gather_bilinear_f32(flat.data_ptr(), height * width, channels, index.data_ptr(),
                                                    weight.data_ptr(), index.shape[1], out.data_ptr()):
                return out  # else an index is out of range: the torch path raises torch's error
        out = flat.index_select(0, index[0]) * weight[0, :, None]
        for k in range(1, 4):
            out.addcmul_(flat.index_select(0, index[k]), weight[k, :, None])
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        index, weight = ctx.saved_tensors
        _, channels, height, width = ctx.map_shape
        grad = None
        lib = _native(grad_out, index, weight)
        if lib is not None:
            grad_out, index, weight = grad_out.contiguous(), index.contiguous(), weight.contiguous()
            grad = grad_out.new_empty(height * width, channels)  # zeroed by the kernel
            if lib.deliffas_scatter_bilinear_f32(grad_out.data_ptr(), height * width, channels, index.data_ptr(),
                                                 weight.data_ptr(), index.shape[1], grad.data_ptr()):
                grad = None
        if grad is None:
            grad = grad_out.new_zeros(height * width, channels)
            grad.index_add_(0, index.reshape(-1), (weight[:, :, None] * grad_out[None]).reshape(-1, channels))
        return grad.view(1, height, width, channels).permute(0, 3, 1, 2), None, None


def _sample_one(feature_map: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Sample one (1, C, S, S) map at (M, 2) uv -> (M, C) (a transposed view).

    A channels-last map whose gradient is wanted, sampled at uv that need none (training), takes
    the gather path; anything else ``grid_sample``. Both give the same values."""
    if (feature_map.requires_grad and not uv.requires_grad and torch.is_grad_enabled()
            and feature_map.is_contiguous(memory_format=torch.channels_last)):
        index, weight = bilinear_corners(uv.to(feature_map.dtype), *feature_map.shape[-2:])
        return _GatherBilinear.apply(feature_map, index, weight)
    grid = uv_to_grid(uv.to(feature_map.dtype)).view(1, 1, -1, 2)  # (1, 1, M, 2)
    out = F.grid_sample(feature_map, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0, :].transpose(0, 1)  # (1, C, 1, M) -> (M, C)


def sample_uv(feature_maps: Float[Tensor, "B C Sh Sw"], batch_index: Integer[Tensor, "N"], uv: Float[Tensor, "N 2"]
              ) -> Float[Tensor, "N C"]:
    """Bilinearly sample per-item atlas maps at per-ray uv coordinates.

    One ``grid_sample`` call per batch item present (a (1, 1, M, 2) grid each), so the cost is
    linear in N with no per-ray Python work; N of about 1.2 M rays (a 940 x 1285 frame) is fine.
    Rays are grouped by ``batch_index`` with a stable sort unless already sorted.

    Performance: for spatially incoherent queries on large maps, pass maps in channels_last
    memory format (``feature_maps.contiguous(memory_format=torch.channels_last)``): each texel's
    C values are then adjacent, and on CPU 1.2 M random lookups into a 1024^2 x 32 map take
    ~0.5 s instead of ~2.9 s (2 cores). :meth:`deliffas.models.deliffas.DeliffasModel.encode` stores
    its maps that way. The result is then a contiguous (N, C) tensor.

    Args:
        feature_maps: (B, C, S_h, S_w) float, atlas-space maps (row 0 = v 1).
        batch_index: (N,) long, which map each ray reads, in [0, B).
        uv: (N, 2) float, atlas coordinates in [0, 1]^2 (OBJ convention, v up).

    Returns:
        (N, C) dtype and device of ``feature_maps``; differentiable w.r.t. ``feature_maps`` and
        ``uv``. The result may be a non-contiguous (transposed) view.

    Raises:
        TypeError: an argument is not a tensor (torch-only: it is differentiable and runs where the
            maps are; ``torch.as_tensor`` converts numpy).
        ValueError: on shape mismatch, non-integer ``batch_index`` or an index outside [0, B).
    """
    for name, x in (("feature_maps", feature_maps), ("batch_index", batch_index), ("uv", uv)):
        require_tensor(name, x, "torch.as_tensor converts numpy")
    sizes = check_shape("feature_maps", feature_maps, "B C _ _")
    sizes = check_shape("uv", uv, "N 2", sizes)
    check_shape("batch_index", batch_index, "N", sizes)
    if batch_index.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8, torch.int8):
        raise ValueError(f"batch_index: expected an integer tensor, got dtype {batch_index.dtype}")
    num_batch, channels = sizes["B"], sizes["C"]
    num_rays = sizes["N"]
    if num_rays == 0:
        return feature_maps.new_zeros(0, channels)
    if num_batch == 1:
        if bool((batch_index != 0).any()):
            raise ValueError("batch_index: values must be 0 when feature_maps has B = 1")
        return _sample_one(feature_maps, uv)

    batch_index = batch_index.long()
    lo, hi = int(batch_index.min()), int(batch_index.max())
    if lo < 0 or hi >= num_batch:
        raise ValueError(f"batch_index: values must lie in [0, {num_batch}), got range [{lo}, {hi}]")
    is_sorted = bool((batch_index[1:] >= batch_index[:-1]).all())
    order = None if is_sorted else torch.argsort(batch_index, stable=True)
    uv_sorted = uv if order is None else uv[order]
    counts = torch.bincount(batch_index, minlength=num_batch).tolist()
    pieces = []
    for b, uv_b in enumerate(torch.split(uv_sorted, counts)):
        if counts[b]:
            pieces.append(_sample_one(feature_maps[b : b + 1], uv_b))
    sampled = torch.cat(pieces, dim=0)  # (N, C) in sorted order
    if order is None:
        return sampled
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(num_rays, device=order.device)
    return sampled.index_select(0, inverse)
