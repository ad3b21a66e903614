"""The U-Net's first and final layers in training with gradients from C loops (models.unet_grad), and
the training thresholds of the matrix-product path (models.unet_cpu): the values of torch's own autograd."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from deliffas.models import unet_grad
from deliffas.models.unet_grad import (conv_k4s2_input_fixed, conv_transpose_k4s2, native_conv_grad_applies,
                                       native_grad_applies)
from deliffas.native import LazyLibrary, NativeLibrary


def _kernel_or_skip():
    built = unet_grad._KERNEL.load()
    if built.lib is None and built.reason.startswith(("disabled", "no C compiler")):
        pytest.skip(built.reason)
    assert built.lib is not None, built.reason  # this project's machines have a compiler


def _case(side: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(1, 16, side, side, generator=gen).contiguous(memory_format=torch.channels_last)
    w = torch.randn(16, 16, 4, 4, generator=gen) * 0.1
    b = torch.randn(16, generator=gen)
    g = torch.randn(1, 16, 2 * side, 2 * side, generator=gen).contiguous(memory_format=torch.channels_last)
    return x, w, b, g


def _grads(fn, x, w, b, g):
    x, w, b = (t.clone().requires_grad_() for t in (x, w, b))
    y = fn(x, w, b)
    y.backward(g)
    return y.detach(), x.grad, w.grad, b.grad


@pytest.mark.parametrize("side", [1, 2, 7, 16, 33])
def test_the_c_gradients_equal_torchs(side):
    """Every position of the map (the edges' missing taps, rows and columns of any length) against torch's
    convolution backward, up to float summation order; the forward is torch's own."""
    _kernel_or_skip()
    case = _case(side)
    torch_out = _grads(lambda x, w, b: F.conv_transpose2d(x, w, b, stride=2, padding=1), *case)
    c_out = _grads(conv_transpose_k4s2, *case)
    assert torch.equal(torch_out[0], c_out[0])
    for ref, got in zip(torch_out[1:], c_out[1:]):
        torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))
    assert c_out[1].is_contiguous(memory_format=torch.channels_last)
    again = _grads(conv_transpose_k4s2, *case)
    assert all(torch.equal(a, b) for a, b in zip(c_out, again))  # a fixed order: deterministic


def test_the_c_gradients_apply_only_where_built():
    _kernel_or_skip()
    x, w, _, _ = _case(8)
    args = ((2, 2), (1, 1), (0, 0), 1, (1, 1))
    assert native_grad_applies(x, w, *args) == unet_grad.wide_vectors()  # AVX-512 builds only (else slower)
    assert not native_grad_applies(x.contiguous(), w, *args)  # NCHW
    assert not native_grad_applies(x.double(), w.double(), *args)
    assert not native_grad_applies(x[:, :8], w[:8], *args)  # 8 -> 16 channels: no loop built
    assert not native_grad_applies(x, w, (1, 1), (1, 1), (0, 0), 1, (1, 1))


def test_the_unet_trains_its_first_and_final_layers_through_the_c_gradients(monkeypatch):
    """The ``small`` preset's U-Net: the parameter gradients of one training forward and backward with the C
    loops equal those without them, up to float summation order."""
    from deliffas.models.unet import UNet, UNetConfig

    _kernel_or_skip()
    torch.manual_seed(0)
    net = UNet(UNetConfig(in_channels=9, out_channels=16, base_channels=8, max_channels=64, norm="affine"), 64)
    x = torch.rand(1, 9, 64, 64)
    g = torch.randn(1, 16, 64, 64)
    calls = []
    for fn in (unet_grad._ConvTransposeK4S2, unet_grad._ConvK4S2InputFixed):
        monkeypatch.setattr(fn, "backward", (lambda real: lambda ctx, grad: calls.append(1) or real(ctx, grad))(
            fn.backward))

    def grads():
        net.zero_grad()
        net(x).backward(g)
        return {k: p.grad.clone() for k, p in net.named_parameters()}

    with_c = grads()
    expected = [1, 1] if unet_grad.wide_vectors() else [1]  # the final layer's (AVX-512) and the first layer's
    assert calls == expected
    unavailable = LazyLibrary("conv_transpose_grad", unet_grad._KERNEL.source, fallback="torch")
    monkeypatch.setattr(unavailable, "_built", NativeLibrary(None, "test: no compiler"))
    monkeypatch.setattr(unet_grad, "_KERNEL", unavailable)
    plain = grads()
    assert calls == expected  # torch's autograd this time
    for k in plain:
        torch.testing.assert_close(with_c[k], plain[k], rtol=1e-4, atol=1e-5 * float(plain[k].abs().max()) + 1e-12)


def test_training_takes_onednn_for_mid_size_maps():
    """Under autograd, 16 x 16 convolutions and 8 x 8 transposed ones leave the matrix-product path (oneDNN's
    forward and backward are faster there); inference keeps it."""
    from deliffas.models.unet_conv import Conv2d, ConvTranspose2d
    from deliffas.models.unet_cpu import gemm_ok

    conv, up = Conv2d(64, 64, 4, 2, 1, bias=False), ConvTranspose2d(128, 64, 4, 2, 1, bias=False)
    x16, x8, x4 = torch.rand(1, 64, 16, 16), torch.rand(1, 128, 8, 8), torch.rand(1, 128, 4, 4)
    assert not gemm_ok(x16, conv) and not gemm_ok(x8, up) and gemm_ok(x4, up)
    with torch.no_grad():
        assert gemm_ok(x16, conv) and gemm_ok(x8, up)
    conv.weight.requires_grad_(False)  # frozen weights: the inference choice
    assert gemm_ok(x16, conv)


def test_without_a_bias():
    _kernel_or_skip()
    x, w, _, g = _case(5)
    xa, wa = x.clone().requires_grad_(), w.clone().requires_grad_()
    F.conv_transpose2d(xa, wa, None, stride=2, padding=1).backward(g)
    xb, wb = x.clone().requires_grad_(), w.clone().requires_grad_()
    conv_transpose_k4s2(xb, wb, None).backward(g)
    torch.testing.assert_close(xb.grad, xa.grad, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(wb.grad, wa.grad, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("side", [2, 8, 38])
def test_the_first_layers_weight_gradient_equals_torchs(side):
    """A 9 -> 8 convolution (kernel 4, stride 2, padding 1) on a map that needs no gradient: torch's forward and,
    up to float summation order, torch's weight gradient; other cases are left to torch."""
    _kernel_or_skip()
    gen = torch.Generator().manual_seed(side)
    x = torch.rand(1, 9, side, side, generator=gen).contiguous(memory_format=torch.channels_last)
    w = torch.randn(8, 9, 4, 4, generator=gen) * 0.1
    g = torch.randn(1, 8, side // 2, side // 2, generator=gen).contiguous(memory_format=torch.channels_last)
    assert native_conv_grad_applies(x, w, (2, 2), (1, 1), 1, (1, 1))
    wa, wb = w.clone().requires_grad_(), w.clone().requires_grad_()
    ya, yb = F.conv2d(x, wa, None, 2, 1), conv_k4s2_input_fixed(x, wb)
    ya.backward(g)
    yb.backward(g)
    assert torch.equal(ya, yb)
    torch.testing.assert_close(wb.grad, wa.grad, rtol=1e-5, atol=1e-5 * float(wa.grad.abs().max()))
    args = ((2, 2), (1, 1), 1, (1, 1))
    assert not native_conv_grad_applies(x.clone().requires_grad_(), w, *args)  # an input that needs a gradient
    assert not native_conv_grad_applies(x[..., :-1], w, *args)  # an odd side
    assert not native_conv_grad_applies(x.contiguous(), w, *args)
    assert not native_conv_grad_applies(x, w[:4], *args)
