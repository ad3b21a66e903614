"""The U-Nets' output sigmoid in training, with the saturation penalty on its logits alongside.

:func:`sigmoid_with_penalty` returns ``sigmoid(s)`` and ``mean(relu(|s| - m)^2)``
(:func:`deliffas.models.losses.saturation_penalty` of the one map) from one autograd node, whose backward writes
the logits' gradient ``g y (1 - y) + 2 (s - clamp(s, -m, m)) c`` in one pass over the map (``csrc/feature_sigmoid.c``
on CPU float32): the sigmoid's backward, the penalty's and the sum autograd would form of the two, each of them
a pass over a (1, C, S, S) map otherwise. The gradient is the same to the bit as the separate nodes' (the same
float32 roundings in the same order; the tests compare them); the penalty's value, which only the logs read, is
summed in another order.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from deliffas.models.losses import saturation_penalty
from deliffas.native import LazyLibrary

__all__ = ["sigmoid_with_penalty"]


_KERNEL = LazyLibrary("feature_sigmoid", "feature_sigmoid.c",  # signatures: feature_sigmoid.h
                      fallback="torch's sigmoid backward and softshrink, one pass each")


def _dense_like(*maps: torch.Tensor) -> bool:
    """Whether the maps are CPU float32, dense and laid out alike (one flat loop visits the same elements)."""
    first = maps[0]
    return all(m.device.type == "cpu" and m.dtype == torch.float32 and m.shape == first.shape
               and m.stride() == first.stride() for m in maps) and (
        first.is_contiguous() or first.is_contiguous(memory_format=torch.channels_last))


class _SigmoidWithPenalty(torch.autograd.Function):
    @staticmethod
    def forward(ctx, logits: torch.Tensor, margin: float) -> tuple[torch.Tensor, torch.Tensor]:
        features = torch.sigmoid(logits)
        ctx.save_for_backward(logits, features)
        ctx.margin = margin
        ctx.set_materialize_grads(False)
        lib = _KERNEL.get() if _dense_like(logits) else None
        if lib is not None:
            total = lib.deliffas_beyond_margin_sq_f32(logits.data_ptr(), logits.numel(), margin)
            return features, logits.new_tensor(total / max(logits.numel(), 1))
        return features, saturation_penalty([logits], margin)  # without the kernel: the penalty's own forward

    @staticmethod
    def backward(ctx, grad_features: torch.Tensor | None, grad_penalty: torch.Tensor | None):
        logits, features = ctx.saved_tensors
        if grad_penalty is None:
            grad = None if grad_features is None else torch.ops.aten.sigmoid_backward(grad_features, features)
            return grad, None
        scale = 2 * grad_penalty / max(logits.numel(), 1)  # as the penalty's own backward forms it
        if grad_features is None:
            return F.softshrink(logits, ctx.margin) * scale, None
        lib = _KERNEL.get() if _dense_like(logits, features, grad_features) else None
        if lib is None:
            sigmoid_grad = torch.ops.aten.sigmoid_backward(grad_features, features)
            return sigmoid_grad + F.softshrink(logits, ctx.margin) * scale, None
        grad = torch.empty_like(logits)
        lib.deliffas_sigmoid_saturation_backward_f32(grad_features.data_ptr(), features.data_ptr(), logits.data_ptr(),
                                                     logits.numel(), ctx.margin, float(scale), grad.data_ptr())
        return grad, None


def sigmoid_with_penalty(logits: torch.Tensor, margin: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``sigmoid(logits)`` and the saturation penalty ``mean(relu(|logits| - margin)^2)``, as one autograd node.

    Args:
        logits: a U-Net's final-layer output, any shape (channels-last maps stay channels-last).
        margin: |s| allowed without penalty (> 0).

    Returns:
        (features, penalty): the sigmoid, shaped as ``logits``, and a () tensor.
    """
    if margin <= 0:
        raise ValueError(f"sigmoid_with_penalty: margin must be > 0, got {margin}")
    return _SigmoidWithPenalty.apply(logits, float(margin))
