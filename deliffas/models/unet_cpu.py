"""The CPU side of the U-Net's inference: map layouts, the compiled channels_last conversion, huge-page
output maps and the fused per-channel :class:`Epilogue` (a block's folded norm and activation).

Shared by the layers (:mod:`deliffas.models.unet_conv`) and their prepacked oneDNN path
(:mod:`deliffas.models.unet_prepack`).
"""

from __future__ import annotations

import ctypes
import logging
import sys
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from deliffas.native import LazyLibrary

logger = logging.getLogger(__name__)

GEMM_MAX_PIXELS = 8 * 8
"""On CPU, every transposed convolution whose input has at most this many pixels runs as one
matrix product with the input followed by ``fold`` (col2im). These deep layers are bound by
reading their large weights (16-32 MB each at 512 channels), which oneDNN re-lays out on every
call; the product reads them once."""

CONV_GEMM_MAX_PIXELS = 16 * 16
"""The same for convolutions (one matrix product with the unfolded input): faster than oneDNN up to
16 x 16 inputs, where the weights outweigh the map."""

TRAINING_GEMM_MAX_PIXELS = 4 * 4
TRAINING_CONV_GEMM_MAX_PIXELS = 8 * 8
"""``GEMM_MAX_PIXELS`` and ``CONV_GEMM_MAX_PIXELS`` for a layer whose weights need a gradient (training): there
oneDNN's forward and backward together beat the matrix product and its backward (``fold`` / ``unfold``) on
16 x 16 convolutions and 8 x 8 transposed ones (the ``small`` preset's two U-Nets at S = 256: with the final
layer's C gradients, :mod:`deliffas.models.unet_grad`, 2.8 ms of a 60 ms step)."""

CHANNELS_LAST_MIN_PIXELS = 32 * 32
"""On CPU, every convolution whose input has at least this many pixels runs in channels_last
memory format: oneDNN is much faster there in that layout (e.g. the first 9 -> 16
convolution at 1024^2), while the deep, small maps are faster in the default layout."""

CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS = 16 * 16
"""The same for transposed convolutions, which are faster in channels_last from 16 x 16 inputs on."""


@dataclass(frozen=True)
class Epilogue:
    """Per-channel ``act(y * scale + shift)`` fused into a convolution outside autograd.

    ``scale`` and ``shift`` are (C_out,) tensors (or a float scale) or None; ``act`` is None,
    ``"relu"``, ``"leaky_relu"`` (slope ``slope``) or ``"sigmoid"``. ``sources`` are the tensors
    (and numbers) that tensor-valued ``scale`` and ``shift`` are computed from, e.g. a norm's
    parameters and running statistics: prepacked weights stay valid while these are the same
    objects at the same version (:func:`~deliffas.models.unet_prepack.packed_conv`), which is cheaper
    than comparing values."""

    scale: torch.Tensor | float | None = None
    shift: torch.Tensor | None = None
    act: str | None = None
    slope: float = 0.0
    sources: tuple = ()

    def __post_init__(self) -> None:
        if (isinstance(self.scale, torch.Tensor) or isinstance(self.shift, torch.Tensor)) and not self.sources:
            raise ValueError("Epilogue: tensor scale/shift need the sources they are computed from")

    def apply_(self, y: torch.Tensor) -> torch.Tensor:
        """The epilogue in place on ``y`` (a fresh convolution output)."""
        if self.scale is not None:
            y.mul_(self.scale.view(1, -1, 1, 1) if isinstance(self.scale, torch.Tensor) else self.scale)
        if self.shift is not None:
            y.add_(self.shift.view(1, -1, 1, 1))
        return self.activate_(y)

    def activate_(self, y: torch.Tensor) -> torch.Tensor:
        if self.act == "relu":
            y.relu_()
        elif self.act == "leaky_relu":
            F.leaky_relu_(y, self.slope)
        elif self.act == "sigmoid":
            y.sigmoid_()
        elif self.act is not None:
            raise ValueError(f"Epilogue: unknown activation {self.act!r}")
        return y

    def folded(
        self, weight: torch.Tensor, bias: torch.Tensor | None, out_dim: int
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(weight * scale, bias * scale + shift)`` with the scale along ``weight``'s dim ``out_dim``
        (fresh tensors when they differ from the inputs); the convolution then computes
        ``y * scale + shift`` up to float rounding."""
        scale, shift = self.scale, self.shift
        if scale is not None:
            if isinstance(scale, torch.Tensor):
                shape = [1] * weight.dim()
                shape[out_dim] = -1
                weight = weight * scale.view(shape)
            else:
                weight = weight * scale
            if bias is not None:
                bias = bias * scale
        if shift is not None:
            bias = shift if bias is None else bias + shift
        return weight, bias


def cpu_layout(x: torch.Tensor, min_pixels: int | None = None) -> torch.Tensor:
    """On CPU: ``x`` in channels_last when it has at least ``min_pixels`` pixels (default
    ``CHANNELS_LAST_MIN_PIXELS``), else in the default layout (a channels_last input would make
    torch copy the large weights of the deep layers to channels_last on every call). Elsewhere:
    ``x`` unchanged."""
    if x.device.type != "cpu":
        return x
    if x.shape[-2] * x.shape[-1] >= (CHANNELS_LAST_MIN_PIXELS if min_pixels is None else min_pixels):
        return channels_last(x)
    return x.contiguous()


_LAYOUT_KERNEL = LazyLibrary("unet_layout", "unet_layout.c",  # signatures: unet_layout.h
                             fallback="torch's channels_last copy for the U-Net input, slower")


def channels_last(x: torch.Tensor) -> torch.Tensor:
    """``x`` (N, C, H, W) in channels_last memory format (``x`` itself when it already is).

    A dense float32 CPU map in the default layout (the U-Net's input) is converted by a compiled
    loop into a fresh :func:`new_map`, faster than torch's copy, the same values. Other inputs, inputs that autograd tracks, or
    without a C compiler (or with ``DELIFFAS_NATIVE=0``, see :mod:`deliffas.native`), use torch's
    copy."""
    if x.is_contiguous(memory_format=torch.channels_last):
        return x
    no_grad = not (x.requires_grad and torch.is_grad_enabled())  # the compiled copy has no backward
    if no_grad and x.device.type == "cpu" and x.dtype == torch.float32 and x.dim() == 4 and x.is_contiguous():
        lib = _LAYOUT_KERNEL.get()
        if lib is not None:
            n, c, h, w = x.shape
            out = new_map(x, c, h, w, channels_last=True)
            lib.deliffas_planar_to_interleaved_f32(x.data_ptr(), out.data_ptr(), n, c, h * w)
            return out
    return x.contiguous(memory_format=torch.channels_last)


HUGE_PAGE_MIN_BYTES = 4 << 20
"""Fresh CPU maps of at least this size that the U-Net allocates itself (skip concatenations, the
channels_last copy of the input) are advised to the kernel as transparent huge pages (Linux
``madvise(MADV_HUGEPAGE)``; a no-op elsewhere or when THP is disabled). Their pages are touched
first by the U-Net's own writes, which otherwise fault in one 4 kB page at a time (in a VM, a
noticeable part of the paper U-Net's time at 1024^2, e.g. for the 64 MB concatenation before its
last layer)."""

_MADV_HUGEPAGE = 14
_HUGE_PAGE = 2 << 20
_madvise = None


def _advise_huge_pages(t: torch.Tensor) -> torch.Tensor:
    """Advise the 2 MB-aligned pages inside ``t``'s (fresh, untouched) memory as huge pages."""
    global _madvise
    nbytes = t.numel() * t.element_size()
    if t.device.type != "cpu" or nbytes < HUGE_PAGE_MIN_BYTES or not sys.platform.startswith("linux"):
        return t
    if _madvise is None:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
            libc.madvise.restype = ctypes.c_int
            _madvise = libc.madvise
        except (OSError, AttributeError):
            _madvise = False
    if _madvise:
        start = -(-t.data_ptr() // _HUGE_PAGE) * _HUGE_PAGE
        end = (t.data_ptr() + nbytes) // _HUGE_PAGE * _HUGE_PAGE
        if end > start:
            _madvise(start, end - start, _MADV_HUGEPAGE)  # advice only: failure changes nothing
    return t


def new_map(
    like: torch.Tensor, channels: int, height: int, width: int, channels_last: bool | None = None
) -> torch.Tensor:
    """Uninitialised (B, channels, height, width) map on ``like``'s device and dtype, in the
    layout :func:`cpu_layout` gives a map of that size (or channels_last if asked), advised as
    huge pages when large."""
    if channels_last is None:
        channels_last = height * width >= CHANNELS_LAST_MIN_PIXELS
    b = like.shape[0]
    numel, item = b * channels * height * width, like.element_size()
    if like.device.type != "cpu" or numel * item < HUGE_PAGE_MIN_BYTES:
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        return torch.empty((b, channels, height, width), dtype=like.dtype, device=like.device, memory_format=fmt)
    # one flat buffer with 2 MB of slack, used from its first 2 MB boundary on: every page of the map
    # can then be a huge page
    flat = torch.empty(numel + _HUGE_PAGE // item, dtype=like.dtype, device=like.device)
    start = (-flat.data_ptr() % _HUGE_PAGE) // item
    flat = _advise_huge_pages(flat[start : start + numel])
    if channels_last:
        return flat.view(b, height, width, channels).permute(0, 3, 1, 2)
    return flat.view(b, channels, height, width)


def gemm_ok(x: torch.Tensor, conv: nn.Module) -> bool:
    """Whether ``conv`` on ``x`` takes the matrix-product path (small CPU maps, plain convolution)."""
    transposed = isinstance(conv, nn.ConvTranspose2d)
    if torch.is_grad_enabled() and conv.weight.requires_grad:
        max_pixels = TRAINING_GEMM_MAX_PIXELS if transposed else TRAINING_CONV_GEMM_MAX_PIXELS
    else:
        max_pixels = GEMM_MAX_PIXELS if transposed else CONV_GEMM_MAX_PIXELS
    return (
        x.device.type == "cpu"
        and x.dim() == 4
        and x.shape[-2] * x.shape[-1] <= max_pixels
        and conv.groups == 1
        and conv.dilation == (1, 1)
        and conv.padding_mode == "zeros"
        and isinstance(conv.padding, tuple)
    )


def finish_output(y: torch.Tensor, epilogue: Epilogue | None, out: torch.Tensor | None) -> torch.Tensor:
    """Apply ``epilogue`` in place on the fresh output ``y``, then copy it into ``out`` if given."""
    if epilogue is not None:
        epilogue.apply_(y)
    if out is None:
        return y
    out.copy_(y)
    return out


def check_fused(epilogue: Epilogue | None, out: torch.Tensor | None) -> None:
    if (epilogue is not None or out is not None) and torch.is_grad_enabled():
        raise RuntimeError("U-Net conv: epilogue/out are for inference only (torch.no_grad / inference_mode)")


def dense_layout(x: torch.Tensor) -> torch.Tensor:
    """``x`` when it is dense in the default or the channels_last layout, else a default-layout copy."""
    if x.is_contiguous() or x.is_contiguous(memory_format=torch.channels_last):
        return x
    return x.contiguous()
