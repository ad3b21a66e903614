"""The U-Net's convolution layers, tuned for CPU inference.

``Conv2d`` and ``ConvTranspose2d`` are ``nn.Conv2d`` / ``nn.ConvTranspose2d`` with the same
parameters and state_dict, computing the same values up to float rounding, tuned for CPU: large
maps in channels_last, small maps as plain matrix products. Outside autograd they also take an
:class:`~deliffas.models.unet_cpu.Epilogue` (the block's norm, folded into the weights, and its
activation, fused into oneDNN's kernel) and, for transposed convolutions, an ``out`` buffer (the
first half of a skip concatenation), and with a :class:`~deliffas.models.unet_prepack.PrepackCache`
(held by the U-Net after ``optimize_for_inference``) keep each module's folded weights in oneDNN's
blocked layout until they change (:mod:`deliffas.models.unet_prepack`). The map layouts and
epilogues are :mod:`deliffas.models.unet_cpu`. On other devices the layers are plain torch.
"""

from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from torch import nn

from deliffas.models.unet_cpu import (
    CHANNELS_LAST_MIN_PIXELS,
    CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS,
    Epilogue,
    channels_last,
    check_fused,
    cpu_layout,
    dense_layout,
    finish_output,
    gemm_ok,
)
from deliffas.models.unet_grad import (conv_k4s2_input_fixed, conv_transpose_k4s2, native_conv_grad_applies,
                                       native_grad_applies)
from deliffas.models.unet_prepack import PrepackCache, onednn_act, packed_conv

logger = logging.getLogger(__name__)


class Conv2d(nn.Conv2d):
    """``nn.Conv2d`` (same parameters, same result up to float rounding) tuned for CPU: large maps
    in channels_last, small maps as one matrix product of the weights with the unfolded input.

    Outside autograd, ``forward(x, epilogue=...)`` also applies a per-channel scale, shift and
    activation (the U-Net's norm and LeakyReLU) to the result, with weights prepacked into
    ``prepacked`` when given."""

    def forward(
        self, x: torch.Tensor, *, epilogue: Epilogue | None = None, prepacked: PrepackCache | None = None
    ) -> torch.Tensor:
        check_fused(epilogue, None)
        if epilogue is not None and prepacked is not None:
            # large NCHW maps (the U-Net's input) in channels_last; others as they come
            large = x.shape[-2] * x.shape[-1] >= CHANNELS_LAST_MIN_PIXELS
            y = packed_conv(self, channels_last(x) if large else dense_layout(x), epilogue, prepacked)
            if y is not None:
                return y
        if gemm_ok(x, self):
            return finish_output(self._gemm(x), epilogue, None)
        if epilogue is None:
            x = cpu_layout(x)
            if (torch.is_grad_enabled() and self.weight.requires_grad and self.bias is None
                    and self.padding_mode == "zeros"
                    and native_conv_grad_applies(x, self.weight, self.stride, self.padding, self.groups,
                                                 self.dilation)):
                return conv_k4s2_input_fixed(x, self.weight)  # the same forward, a C loop for the weight gradient
            return super().forward(x)
        h_out = (x.shape[-2] + 2 * self.padding[0] - self.kernel_size[0]) // self.stride[0] + 1
        w_out = (x.shape[-1] + 2 * self.padding[1] - self.kernel_size[1]) // self.stride[1] + 1
        if self.weight.numel() > x.shape[0] * self.out_channels * h_out * w_out:
            return epilogue.apply_(self._conv_forward(cpu_layout(x), self.weight, self.bias))
        # scale and shift folded into the (smaller) weights and bias: no passes over the output
        weight, bias = epilogue.folded(self.weight, self.bias, 0)
        return epilogue.activate_(self._conv_forward(cpu_layout(x), weight, bias))

    def _gemm(self, x: torch.Tensor) -> torch.Tensor:
        b, _, h, w = x.shape
        (kh, kw), (sh, sw), (ph, pw) = self.kernel_size, self.stride, self.padding
        h_out, w_out = (h + 2 * ph - kh) // sh + 1, (w + 2 * pw - kw) // sw + 1
        cols = F.unfold(x, self.kernel_size, padding=self.padding, stride=self.stride)  # (B, C_in kh kw, L)
        weight = self.weight.reshape(self.out_channels, -1)  # (C_out, C_in kh kw)
        # W @ cols with cols transposed in memory (L rows of C_in kh kw values): MKL then streams the
        # weights as dot products (faster than W @ cols for L = 4)
        ys = [torch.mm(weight, cols[i].t().contiguous().t()) for i in range(b)]  # (C_out, L) each
        y = (ys[0].unsqueeze(0) if b == 1 else torch.stack(ys)).reshape(b, self.out_channels, h_out, w_out)
        return y if self.bias is None else y + self.bias.view(1, -1, 1, 1)


class ConvTranspose2d(nn.ConvTranspose2d):
    """``nn.ConvTranspose2d`` (same parameters, same result up to float rounding) tuned for CPU:
    large maps in channels_last, small maps as one matrix product followed by ``fold`` (col2im).

    ``forward(x, scale=k)`` is ``k x forward(x)`` with ``k`` in the weights (the U-Net's training forward).
    Outside autograd, ``forward(x, epilogue=..., out=...)`` also applies a per-channel scale, shift
    and activation (the U-Net's norm and ReLU) and writes the result into ``out`` (e.g. the first
    half of the skip concatenation's buffer), which it returns; weights are prepacked into
    ``prepacked`` when given."""

    def forward(
        self,
        x: torch.Tensor,
        output_size: list[int] | None = None,
        *,
        epilogue: Epilogue | None = None,
        out: torch.Tensor | None = None,
        prepacked: PrepackCache | None = None,
        scale: float = 1.0,
    ) -> torch.Tensor:
        check_fused(epilogue, out)
        if scale != 1.0:  # the U-Net's training forward: its final layer times 2
            if epilogue is not None or out is not None or output_size is not None:
                raise ValueError("ConvTranspose2d: scale takes no epilogue, out or output_size")
            return self._scaled(x, scale)
        if epilogue is not None and prepacked is not None and output_size is None:
            y = packed_conv(self, dense_layout(x), epilogue, prepacked, out)
            if y is not None:
                return y
        if output_size is not None or self.output_padding != (0, 0):
            x = cpu_layout(x, CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS)
            return finish_output(super().forward(x, output_size), epilogue, out)
        if gemm_ok(x, self):
            return finish_output(self._gemm(x), epilogue, out)
        x = cpu_layout(x, CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS)
        if epilogue is None or self.weight.numel() > x.shape[0] * self.out_channels * 4 * x.shape[-2] * x.shape[-1]:
            return finish_output(super().forward(x), epilogue, out)
        # scale and shift folded into the (smaller) weights, the activation into oneDNN's kernel
        weight, bias = epilogue.folded(self.weight, self.bias, 1)
        y = onednn_act(True, x, weight, bias, epilogue, self.padding, self.stride, self.dilation, self.groups,
                        self.output_padding)
        if y is None:
            y = epilogue.activate_(self._conv_transpose(x, weight, bias))
        return finish_output(y, None, out)

    def _scaled(self, x: torch.Tensor, scale: float) -> torch.Tensor:
        """``scale x`` the plain forward with the factor in the weights and bias, not in a pass over the output
        (for a power of two the same values: doubling is exact in floating point)."""
        if self.output_padding != (0, 0):
            return super().forward(x) * scale
        if gemm_ok(x, self):
            return self._gemm(x) * scale
        bias = None if self.bias is None else self.bias * scale
        x = cpu_layout(x, CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS)
        if torch.is_grad_enabled() and native_grad_applies(x, self.weight, self.stride, self.padding,
                                                           self.output_padding, self.groups, self.dilation):
            return conv_transpose_k4s2(x, self.weight * scale, bias)  # the same forward, C loops for the gradients
        return self._conv_transpose(x, self.weight * scale, bias)

    def _conv_transpose(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        return F.conv_transpose2d(x, weight, bias, self.stride, self.padding, self.output_padding, self.groups,
                                  self.dilation)

    def _gemm(self, x: torch.Tensor) -> torch.Tensor:
        b, c_in, h, w = x.shape
        (kh, kw), (sh, sw), (ph, pw) = self.kernel_size, self.stride, self.padding
        h_out, w_out = (h - 1) * sh - 2 * ph + kh, (w - 1) * sw - 2 * pw + kw
        xm = x.reshape(b, c_in, h * w)
        weight = self.weight.reshape(c_in, -1)  # (C_in, C_out kh kw)
        # x^T @ W (MKL streams W's rows; W^T @ x is much slower for 4-pixel maps)
        cols = [torch.mm(xm[i].t(), weight) for i in range(b)]  # (H W, C_out kh kw) each
        cols_t = (cols[0].unsqueeze(0) if b == 1 else torch.stack(cols)).transpose(1, 2)
        y = F.fold(cols_t, (h_out, w_out), self.kernel_size, padding=self.padding, stride=self.stride)
        return y if self.bias is None else y + self.bias.view(1, -1, 1, 1)
