"""The U-Net's first and final layers in training with their gradients from C loops.

A transposed convolution with kernel 4, stride 2 and padding 1 on a channels-last CPU float32 map runs its
forward as before (``F.conv_transpose2d``, oneDNN) and takes its input, weight and bias gradients from
``csrc/conv_transpose_grad.c`` (:func:`conv_transpose_k4s2`): oneDNN's backward for the final 16 -> 16 layer
on 128 -> 256 pixel maps runs well below the machine's FMA rate. The first layer, a convolution of the same
kernel whose input (the normal maps) needs no gradient, likewise takes its weight gradient from a C loop
(:func:`conv_k4s2_input_fixed`). The gradients are the exact sums in another order (FMA contraction, a fixed
order: deterministic); the tests compare them with torch's. Other shapes, layouts, dtypes and devices, or no C
compiler: torch's autograd as before. The transposed convolution's loops run on 16-float vectors and are used
only where the build has AVX-512 (:func:`wide_vectors`); the first layer's run on 8-float vectors (AVX2 too).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from deliffas.native import LazyLibrary

__all__ = ["conv_k4s2_input_fixed", "conv_transpose_k4s2", "native_conv_grad_applies", "native_grad_applies",
           "wide_vectors"]


_KERNEL = LazyLibrary("conv_transpose_grad", "conv_transpose_grad.c", flags=("-ffp-contract=fast", "-Wno-psabi"),
                      fallback="torch's convolution backward")  # signatures: conv_transpose_grad.h


def wide_vectors() -> bool:
    """Whether the transposed convolution's C gradients run here: built with AVX-512, whose 16-float registers
    their loops are written for (without it they run several times slower than oneDNN's backward)."""
    lib = _KERNEL.get()
    return lib is not None and bool(lib.deliffas_conv_transpose_grad_wide_vectors())

CHANNELS = frozenset({(16, 16)})
"""(input, output) channel pairs the C loops are built for: the final layer of the ``small`` and ``realtime``
presets' U-Nets (for their 32 -> 8 and 64 -> 16 layers below it oneDNN's backward was as fast)."""


CONV_CHANNELS = frozenset({(9, 8)})
"""(input, output) channel pairs of a convolution whose input needs no gradient that the C weight gradient is
built for: the ``small`` and ``realtime`` presets' first layer (temporal normal maps of 3 frames in)."""


def _channels_last(t: torch.Tensor) -> bool:
    return t.dim() == 4 and t.shape[0] == 1 and t.is_contiguous(memory_format=torch.channels_last)


def native_grad_applies(x: torch.Tensor, weight: torch.Tensor, stride, padding, output_padding, groups,
                        dilation) -> bool:
    """Whether :func:`conv_transpose_k4s2` takes the C gradients for this call (else it is plain torch)."""
    return (x.device.type == "cpu" and x.dtype == torch.float32 and weight.dtype == torch.float32
            and _channels_last(x) and tuple(weight.shape[2:]) == (4, 4) and tuple(stride) == (2, 2)
            and tuple(padding) == (1, 1) and tuple(output_padding) == (0, 0) and groups == 1
            and tuple(dilation) == (1, 1) and (int(weight.shape[0]), int(weight.shape[1])) in CHANNELS
            and wide_vectors())


class _ConvTransposeK4S2(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return F.conv_transpose2d(x, weight, bias, stride=2, padding=1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight = ctx.saved_tensors
        ci, co = int(weight.shape[0]), int(weight.shape[1])
        h, w = int(x.shape[2]), int(x.shape[3])
        lib = _KERNEL.get()
        g = grad.contiguous(memory_format=torch.channels_last)
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            wt = weight.permute(2, 3, 1, 0).contiguous()  # (ky, kx, co, ci)
            grad_x = torch.empty_like(x, memory_format=torch.channels_last)
            if lib.deliffas_conv_transpose_k4s2_input_grad_f32(g.data_ptr(), wt.data_ptr(), h, w, ci, co,
                                                               grad_x.data_ptr()):
                raise RuntimeError(f"conv_transpose_grad: no input-gradient loop for {ci} -> {co} channels")
        want_bias = ctx.has_bias and ctx.needs_input_grad[2]
        if ctx.needs_input_grad[1] or want_bias:  # the bias gradient comes with the weight gradient's pass
            dwt = weight.new_empty(4, 4, ci, co)
            grad_b = weight.new_empty(co) if want_bias else None
            db = None if grad_b is None else grad_b.data_ptr()
            if lib.deliffas_conv_transpose_k4s2_weight_grad_f32(x.data_ptr(), g.data_ptr(), h, w, ci, co,
                                                                dwt.data_ptr(), db):
                raise RuntimeError(f"conv_transpose_grad: no weight-gradient loop for {ci} -> {co} channels")
            grad_w = dwt.permute(2, 3, 0, 1) if ctx.needs_input_grad[1] else None  # (ci, co, ky, kx)
        return grad_x, grad_w, grad_b


def conv_transpose_k4s2(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride=2, padding=1)`` whose backward runs the C loops; call it
    where :func:`native_grad_applies` holds (a (1, CI, H, W) channels-last float32 CPU map, (CI, CO, 4, 4)
    weights)."""
    return _ConvTransposeK4S2.apply(x, weight, bias)


def native_conv_grad_applies(x: torch.Tensor, weight: torch.Tensor, stride, padding, groups, dilation) -> bool:
    """Whether :func:`conv_k4s2_input_fixed` takes the C weight gradient for this call: a (1, CI, H, W)
    channels-last float32 CPU map of even sides that needs no gradient, (CO, CI, 4, 4) weights, stride 2, padding 1."""
    return (x.device.type == "cpu" and x.dtype == torch.float32 and weight.dtype == torch.float32
            and not x.requires_grad and _channels_last(x) and x.shape[2] % 2 == 0 and x.shape[3] % 2 == 0
            and tuple(weight.shape[2:]) == (4, 4) and tuple(stride) == (2, 2) and tuple(padding) == (1, 1)
            and groups == 1 and tuple(dilation) == (1, 1)
            and (int(weight.shape[1]), int(weight.shape[0])) in CONV_CHANNELS and _KERNEL.get() is not None)


class _ConvK4S2InputFixed(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x)
        ctx.channels = int(weight.shape[1]), int(weight.shape[0])
        return F.conv2d(x, weight, None, stride=2, padding=1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (x,) = ctx.saved_tensors
        ci, co = ctx.channels
        g = grad.contiguous(memory_format=torch.channels_last)
        dwt = x.new_empty(4, 4, ci, co)
        if _KERNEL.get().deliffas_conv_k4s2_weight_grad_f32(x.data_ptr(), g.data_ptr(), int(x.shape[2]),
                                                             int(x.shape[3]), ci, co, dwt.data_ptr()):
            raise RuntimeError(f"conv_transpose_grad: no convolution weight-gradient loop for {ci} -> {co} channels")
        return None, dwt.permute(3, 2, 0, 1)  # (co, ci, ky, kx)


def conv_k4s2_input_fixed(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``F.conv2d(x, weight, stride=2, padding=1)`` whose weight gradient runs the C loop (the input gets none);
    call it where :func:`native_conv_grad_applies` holds."""
    return _ConvK4S2InputFixed.apply(x, weight)
