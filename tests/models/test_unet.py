"""Tests of deliffas.models.unet."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from deliffas.models.unet import UNet, UNetConfig, resolve_levels, unet_channels


def test_levels_follow_atlas_side():
    cfg = UNetConfig(in_channels=9)
    assert resolve_levels(cfg, 32) == 5
    assert resolve_levels(cfg, 128) == 7
    assert resolve_levels(cfg, 1024) == 10
    assert unet_channels(cfg, 10) == [16, 32, 64, 128, 256, 512, 512, 512, 512, 512]
    net = UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16), 64)
    assert net.levels == 6 and len(net.down) == 6 and len(net.up) == 5
    assert net.channels == [4, 8, 16, 16, 16, 16]


def test_fewer_levels_and_bad_sizes():
    net = UNet(UNetConfig(in_channels=3, base_channels=4, max_channels=8, levels=3), 32)
    assert net.levels == 3
    assert net(torch.randn(1, 3, 32, 32)).shape == (1, 32, 32, 32)
    with pytest.raises(ValueError, match="power-of-two"):
        UNet(UNetConfig(in_channels=3), 48)
    with pytest.raises(ValueError, match="divisible"):
        UNet(UNetConfig(in_channels=3, levels=5), 48)
    with pytest.raises(ValueError, match="divisible"):
        net(torch.randn(1, 3, 36, 36))
    with pytest.raises(ValueError, match="expected shape"):
        net(torch.randn(1, 4, 32, 32))


def test_shape_range_and_gradients(device):
    net = UNet(UNetConfig(in_channels=9, out_channels=6, base_channels=4, max_channels=16), 32).to(device)
    x = torch.randn(2, 9, 32, 32, device=device, requires_grad=True)
    y = net(x)
    assert y.shape == (2, 6, 32, 32)
    assert y.min() >= 0 and y.max() <= 1
    y.square().mean().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert net.down[0][0].weight.grad.abs().sum() > 0


def test_block_structure():
    cfg = UNetConfig(in_channels=9, base_channels=4, max_channels=16, dropout=True)
    net = UNet(cfg, 32)
    down0 = net.down[0]
    assert isinstance(down0[0], nn.Conv2d) and down0[0].bias is None
    assert down0[0].kernel_size == (4, 4) and down0[0].stride == (2, 2)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in down0)
    assert isinstance(down0[-1], nn.LeakyReLU) and down0[-1].negative_slope == pytest.approx(0.3)
    assert any(isinstance(m, nn.BatchNorm2d) for m in net.down[1])
    # innermost block outputs 1 x 1: no BatchNorm there (batch statistics undefined at B = 1)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in net.down[-1])
    dropouts = [any(isinstance(m, nn.Dropout) for m in block) for block in net.up]
    assert dropouts == [True, True, True, False]
    assert not any(isinstance(m, nn.Dropout) for m in UNet(UNetConfig(in_channels=9, base_channels=4), 32).modules())
    assert isinstance(net.final, nn.ConvTranspose2d) and net.final.out_channels == 32


def test_batch_one_trains_with_one_by_one_bottleneck():
    net = UNet(UNetConfig(in_channels=3, base_channels=4, max_channels=8), 16).train()
    net(torch.randn(1, 3, 16, 16)).mean().backward()  # raises if BatchNorm sees 1 value per channel


@pytest.mark.parametrize("norm", ["affine", "none"])
def test_other_norms(norm):
    net = UNet(UNetConfig(in_channels=3, base_channels=4, max_channels=8, norm=norm), 16)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    assert net(torch.randn(1, 3, 16, 16)).shape == (1, 32, 16, 16)
    with pytest.raises(ValueError, match="norm"):
        UNetConfig(in_channels=3, norm="group")  # type: ignore[arg-type]


def test_init_std():
    net = UNet(UNetConfig(in_channels=9, base_channels=16, max_channels=64), 64)
    weights = torch.cat([m.weight.detach().flatten() for m in net.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))])
    assert abs(float(weights.std()) - 0.02) < 0.002
    assert abs(float(weights.mean())) < 0.002


def test_channels_last_matches():
    torch.manual_seed(0)
    net = UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16), 32).eval()
    x = torch.randn(2, 9, 32, 32)
    ref = net(x)
    net_cl = net.to(memory_format=torch.channels_last)
    out = net_cl(x.contiguous(memory_format=torch.channels_last))
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("size", [1, 2, 8, 16, 32])
@pytest.mark.parametrize("bias", [False, True])
def test_cpu_conv_paths_match_torch(size, bias):
    """The U-Net's conv subclasses (matrix product on small maps, channels_last on large ones)
    compute nn.Conv2d / nn.ConvTranspose2d, forward and backward."""
    from deliffas.models.unet import _Conv2d, _ConvTranspose2d

    torch.manual_seed(0)
    pairs = [(nn.ConvTranspose2d(6, 5, 4, 2, 1, bias=bias), _ConvTranspose2d(6, 5, 4, 2, 1, bias=bias))]
    if size >= 2:
        pairs.append((nn.Conv2d(6, 5, 4, 2, 1, bias=bias), _Conv2d(6, 5, 4, 2, 1, bias=bias)))
    for ref, fast in pairs:
        fast.load_state_dict(ref.state_dict())
        x = torch.randn(2, 6, size, size, requires_grad=True)
        x2 = x.detach().clone().requires_grad_()
        y_ref, y = ref(x), fast(x2)
        torch.testing.assert_close(y, y_ref, rtol=1e-5, atol=1e-6)
        g = torch.randn_like(y_ref)
        y_ref.backward(g)
        y.backward(g)
        torch.testing.assert_close(x2.grad, x.grad, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(fast.weight.grad, ref.weight.grad, rtol=1e-5, atol=1e-5)
