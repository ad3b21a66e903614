"""Tests of deliffas.models.unet."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from deliffas.models.unet import UNet, UNetConfig, optimize_for_inference, resolve_levels, unet_channels


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


def test_block_structure(unchecked):
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
    assert {m.p for m in net.modules() if isinstance(m, nn.Dropout)} == {0.5}  # True: pix2pix's rate
    light = UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16, dropout=0.1), 32)
    assert [m.p for m in light.modules() if isinstance(m, nn.Dropout)] == [0.1, 0.1, 0.1]
    assert not any(isinstance(m, nn.Dropout) for m in UNet(UNetConfig(in_channels=9, base_channels=4, dropout=0.0),
                                                           32).modules())
    for bad in (1.0, -0.1, "0.5"):
        with unchecked(), pytest.raises(ValueError, match="dropout"):  # the config's own check, not the test run's
            UNetConfig(in_channels=9, dropout=bad)
    assert isinstance(net.final, nn.ConvTranspose2d) and net.final.out_channels == 32


def test_batch_one_trains_with_one_by_one_bottleneck():
    net = UNet(UNetConfig(in_channels=3, base_channels=4, max_channels=8), 16).train()
    net(torch.randn(1, 3, 16, 16)).mean().backward()  # raises if BatchNorm sees 1 value per channel


@pytest.mark.parametrize("norm", ["affine", "none"])
def test_other_norms(norm, unchecked):
    net = UNet(UNetConfig(in_channels=3, base_channels=4, max_channels=8, norm=norm), 16)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    assert net(torch.randn(1, 3, 16, 16)).shape == (1, 32, 16, 16)
    with unchecked(), pytest.raises(ValueError, match="norm"):
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
    from deliffas.models.unet_conv import Conv2d, ConvTranspose2d

    torch.manual_seed(0)
    pairs = [(nn.ConvTranspose2d(6, 5, 4, 2, 1, bias=bias), ConvTranspose2d(6, 5, 4, 2, 1, bias=bias))]
    if size >= 2:
        pairs.append((nn.Conv2d(6, 5, 4, 2, 1, bias=bias), Conv2d(6, 5, 4, 2, 1, bias=bias)))
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


def _reference_forward(net: UNet, x: torch.Tensor) -> torch.Tensor:
    """The U-Net in plain torch functional ops on the module's parameters (no CPU paths, no fusion)."""
    import torch.nn.functional as F

    from deliffas.models.unet import _ChannelAffine

    def norm(layers, y):
        for m in layers:
            if isinstance(m, _ChannelAffine):
                y = y * m.weight.view(1, -1, 1, 1) + m.bias.view(1, -1, 1, 1)
            elif isinstance(m, nn.BatchNorm2d):
                y = F.batch_norm(y, m.running_mean, m.running_var, m.weight, m.bias, m.training, 0.0, m.eps)
        return y

    skips = []
    for block in net.down:
        conv = block[0]
        y = norm(block[1:-1], F.conv2d(x, conv.weight, conv.bias, stride=2, padding=1))
        x = F.leaky_relu(y, block[-1].negative_slope)
        skips.append(x)
    x = skips.pop()
    for block in net.up:
        conv = block[0]
        y = norm(block[1:-1], F.conv_transpose2d(x, conv.weight, conv.bias, stride=2, padding=1))
        x = torch.cat([F.relu(y), skips.pop()], dim=1)
    y = F.conv_transpose2d(x, net.final.weight, net.final.bias, stride=2, padding=1)
    return (torch.tanh(y) + 1) / 2


def _randomise_norms(net: UNet) -> None:
    """Norm scales/shifts, BatchNorm statistics and conv biases away from their identity init."""
    from deliffas.models.unet import _ChannelAffine

    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, (_ChannelAffine, nn.BatchNorm2d)):
                m.weight.copy_(torch.rand(m.weight.shape, generator=g) + 0.5)
                m.bias.copy_(torch.rand(m.bias.shape, generator=g) * 0.4 - 0.2)
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.copy_(torch.rand(m.running_mean.shape, generator=g) * 0.2 - 0.1)
                m.running_var.copy_(torch.rand(m.running_var.shape, generator=g) * 1.5 + 0.5)
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)) and m.bias is not None:
                m.bias.copy_(torch.rand(m.bias.shape, generator=g) * 0.2 - 0.1)


@pytest.mark.parametrize("norm", ["affine", "batch", "none"])
@pytest.mark.parametrize("paths", ["all", "unpacked", "plain_torch"])
def test_inference_matches_reference(norm, paths, monkeypatch):
    """The fused inference forward (norms folded into the convs, up blocks written into the skip
    concatenation) computes the U-Net, with prepacked oneDNN weights, with per-call weights, and
    with torch's public ops only."""
    import deliffas.models.unet_prepack as unet_prepack

    if paths != "all":
        monkeypatch.setattr(unet_prepack, "_prepack_ok", False)
    if paths == "plain_torch":
        monkeypatch.setattr(unet_prepack, "_onednn_pointwise_ok", False)
    torch.manual_seed(0)
    net = optimize_for_inference(UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16, norm=norm), 64).eval())
    _randomise_norms(net)
    x = torch.randn(2, 9, 64, 64)
    with torch.no_grad():
        ref = _reference_forward(net, x)
        out = net(x)
    with torch.inference_mode():
        out_im = net(x)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(out_im, ref, rtol=1e-5, atol=2e-6)
    with torch.enable_grad():  # the autograd path (no fusion) agrees too
        torch.testing.assert_close(net(x), ref, rtol=1e-5, atol=2e-6)


def test_inference_unfusable_blocks_use_module_path():
    """BatchNorm with batch statistics and active dropout are not folded: no_grad in training mode
    gives the same values as the reference (batch statistics; dropout off when p = 0)."""
    torch.manual_seed(0)
    net = optimize_for_inference(UNet(UNetConfig(in_channels=3, base_channels=4, max_channels=8, dropout=True), 32).train())
    for m in net.modules():
        if isinstance(m, nn.Dropout):
            m.p = 0.0
    _randomise_norms(net)
    x = torch.randn(2, 3, 32, 32)
    with torch.no_grad():
        ref = _reference_forward(net, x)
        out = net(x)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=2e-6)


def test_conv_hooks_see_original_layers():
    """Every conv module is called once per forward with its usual input and output shapes, fused
    or not (benchmarks count FLOPs with forward hooks)."""
    net = optimize_for_inference(UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16, norm="affine"), 64).eval())
    x = torch.randn(1, 9, 64, 64)
    calls: dict[str, list] = {}

    def hook(name):
        def fn(module, inputs, output):
            calls.setdefault(name, []).append((tuple(inputs[0].shape), tuple(output.shape)))
        return fn

    for name, m in net.named_modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            m.register_forward_hook(hook(name))
    with torch.enable_grad():
        net(x)
    general = {k: v[:] for k, v in calls.items()}
    calls.clear()
    with torch.inference_mode():
        net(x)
    assert calls == general
    assert all(len(v) == 1 for v in calls.values()) and len(calls) == 2 * net.levels


def test_prepacked_weights_follow_changes():
    """The per-module prepacked weights are rebuilt when the conv weights, the norm or the input
    size change (an optimizer step, load_state_dict, a BatchNorm statistics update), never stale;
    they stay out of the state_dict and deepcopy."""
    import copy

    import deliffas.models.unet_prepack as unet_prepack

    torch.manual_seed(0)
    net = optimize_for_inference(UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16, norm="batch"), 32).eval())
    _randomise_norms(net)
    x = torch.randn(1, 9, 32, 32)
    keys = set(net.state_dict())

    def check(inp=x):
        with torch.no_grad():
            torch.testing.assert_close(net(inp), _reference_forward(net, inp), rtol=1e-5, atol=2e-6)

    check()
    if not unet_prepack._prepack_ok:
        pytest.skip("oneDNN prepacked convolutions unavailable in this torch build")
    assert len(net._prepacked) == 2 * net.levels  # every conv, in the U-Net's own cache
    opt = torch.optim.SGD(net.parameters(), lr=0.5)
    net.train()
    net(x).square().mean().backward()  # also moves the BatchNorm running statistics
    opt.step()
    net.eval()
    check()
    other = UNet(net.config, 32)
    net.load_state_dict(other.state_dict())
    check()
    with torch.no_grad():
        net.up[0][1].running_var.mul_(3.0)  # norm only: folded scale changes, conv weights do not
    check()
    check(torch.randn(2, 9, 64, 64))  # another input shape
    assert set(net.state_dict()) == keys
    twin = copy.deepcopy(net)
    with torch.no_grad():
        torch.testing.assert_close(twin(x), net(x))


def _epilogue(channels: int, act: str, slope: float = 0.0):
    from deliffas.models.unet_cpu import Epilogue

    g = torch.Generator().manual_seed(2)
    scale = torch.rand(channels, generator=g) + 0.5
    shift = torch.rand(channels, generator=g) - 0.5
    return Epilogue(scale, shift, act, slope, sources=(scale, shift))


def _apply_reference(y: torch.Tensor, epilogue) -> torch.Tensor:
    import torch.nn.functional as F

    y = y * epilogue.scale.view(1, -1, 1, 1) + epilogue.shift.view(1, -1, 1, 1)
    return F.leaky_relu(y, epilogue.slope) if epilogue.act == "leaky_relu" else F.relu(y)


@pytest.mark.parametrize("lanes", [16, 8, 0])
def test_narrow_layer_forms_match_torch(lanes, monkeypatch):
    """Narrow layers run widened (column pairs for convs, output phases for transposed convs) when
    their output channels fill at most half the SIMD lanes; every form computes the layer with its
    epilogue, into a view of a larger buffer too."""
    import torch.nn.functional as F

    import deliffas.models.unet_conv as unet_conv
    import deliffas.models.unet_prepack as unet_prepack

    if not unet_prepack._prepack_ok or not torch.backends.mkldnn.is_available():
        pytest.skip("oneDNN prepacked convolutions unavailable in this torch build")
    monkeypatch.setattr(unet_prepack, "simd_lanes", lambda: lanes)
    torch.manual_seed(0)
    forms = []
    packs = unet_prepack.PrepackCache()
    for c_out in (4, 8):
        conv = unet_conv.Conv2d(9, c_out, 4, 2, 1, bias=False)
        up = unet_conv.ConvTranspose2d(12, c_out, 4, 2, 1, bias=True)
        with torch.no_grad():
            up.bias.uniform_(-0.1, 0.1)
        for shape in ((2, 9, 64, 64), (1, 9, 64, 62), (1, 9, 32, 32)):  # pairs; odd w_out; 16 x 16 out
            x = torch.randn(shape)
            ep = _epilogue(c_out, "leaky_relu", 0.3)
            with torch.no_grad():
                ref = _apply_reference(F.conv2d(x, conv.weight, None, 2, 1), ep)
                got = conv(x, epilogue=ep, prepacked=packs)
            forms.append((c_out, "conv", unet_prepack._narrow_form(conv, x)))
            torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)
        for shape in ((2, 12, 16, 16), (1, 12, 16, 24), (1, 12, 8, 8)):  # the last has 256 output pixels
            x = torch.randn(shape).contiguous(memory_format=torch.channels_last)
            ep = _epilogue(c_out, "relu")
            h, w = 2 * shape[2], 2 * shape[3]
            cat = torch.full((shape[0], 2 * c_out, h, w), 7.0).contiguous(memory_format=torch.channels_last)
            with torch.no_grad():
                ref = _apply_reference(F.conv_transpose2d(x, up.weight, up.bias, 2, 1), ep)
                got = up(x, epilogue=ep, out=cat[:, :c_out], prepacked=packs)
                fresh = up(x, epilogue=ep, prepacked=packs)
            forms.append((c_out, "up", unet_prepack._narrow_form(up, x)))
            assert got.data_ptr() == cat.data_ptr()
            torch.testing.assert_close(cat[:, :c_out], ref, rtol=1e-5, atol=1e-5)
            torch.testing.assert_close(fresh, ref, rtol=1e-5, atol=1e-5)
            assert bool((cat[:, c_out:] == 7.0).all())  # the skip half is not touched
    expected = {
        16: [(c, "conv", f) for c in (4, 8) for f in ("column_pairs", "direct", "direct")]
        + [(c, "up", f) for c in (4, 8) for f in ("phases", "phases", "transposed")],
        8: [(4, "conv", f) for f in ("column_pairs", "direct", "direct")]
        + [(4, "up", f) for f in ("phases", "phases", "transposed")]
        + [(8, "conv", "direct")] * 3 + [(8, "up", "transposed")] * 3,
        0: [(c, "conv", "direct") for c in (4, 8) for _ in range(3)] + [(c, "up", "transposed") for c in (4, 8) for _ in range(3)],
    }[lanes]
    assert sorted(forms) == sorted(expected)


def test_simd_lanes_follow_the_isa(monkeypatch):
    import deliffas.models.unet_prepack as unet_prepack

    for var in ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX512")
    assert unet_prepack.simd_lanes() == 16
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "avx2")
    assert unet_prepack.simd_lanes() == 8
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX512_CORE_AMX")
    assert unet_prepack.simd_lanes() == 16
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")
    assert unet_prepack.simd_lanes() == 8
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "DEFAULT")
    assert unet_prepack.simd_lanes() == 0


def test_prepacked_weights_follow_affine_norm_changes():
    """The affine norm's scale and shift are the validity sources of the prepacked weights: an
    in-place change or a replaced parameter rebuilds them."""
    from deliffas.models.unet import _ChannelAffine

    torch.manual_seed(0)
    net = optimize_for_inference(UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16, norm="affine"), 64).eval())
    _randomise_norms(net)
    x = torch.randn(1, 9, 64, 64)

    def check():
        with torch.no_grad():
            torch.testing.assert_close(net(x), _reference_forward(net, x), rtol=1e-5, atol=2e-6)

    check()
    norms = [m for m in net.modules() if isinstance(m, _ChannelAffine)]
    with torch.no_grad():
        norms[0].weight.mul_(-2.0)  # in place: same object, new version
        norms[-1].bias.add_(0.3)
    check()
    norms[1].weight = nn.Parameter(norms[1].weight.detach() * 3.0)  # a new object
    check()


@pytest.mark.parametrize("channels", [3, 9, 5])
def test_channels_last_copy(channels, monkeypatch):
    """The U-Net's input conversion (a compiled loop when a C compiler exists) equals torch's
    channels_last copy, without the compiled loop too, and keeps autograd."""
    import deliffas.models.unet_cpu as unet_cpu
    from deliffas.native import NativeLibrary

    x = torch.randn(2, channels, 40, 24)
    ref = x.contiguous(memory_format=torch.channels_last)
    got = unet_cpu.channels_last(x)
    assert got.is_contiguous(memory_format=torch.channels_last) and got.data_ptr() != x.data_ptr()
    assert torch.equal(got, ref)
    assert unet_cpu.channels_last(ref) is ref
    with monkeypatch.context() as m:  # the kernel unavailable, as without a compiler
        m.setattr(unet_cpu._LAYOUT_KERNEL, "_built", NativeLibrary(None, "test: no compiler"))
        m.setattr(unet_cpu._LAYOUT_KERNEL, "_logged", False)
        assert torch.equal(unet_cpu.channels_last(x), ref)
    xg = x.clone().requires_grad_()
    unet_cpu.channels_last(xg).square().sum().backward()
    torch.testing.assert_close(xg.grad, 2 * x)


def test_channels_last_copy_is_compiled_here():
    """On a machine with a C compiler (this project's), the conversion runs the compiled loop."""
    import deliffas.models.unet_cpu as unet_cpu

    built = unet_cpu._LAYOUT_KERNEL.load()
    if built.lib is None and built.reason.startswith(("disabled", "no C compiler")):
        pytest.skip(built.reason)
    assert built.lib is not None, built.reason


def test_prepacked_weights_follow_data_assignment():
    """``param.data = ...`` keeps the parameter's identity and version counter; the prepacked
    weights are rebuilt all the same (keyed by the data pointer too)."""
    torch.manual_seed(0)
    net = optimize_for_inference(UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16, norm="affine"), 64).eval())
    x = torch.randn(1, 9, 64, 64)
    with torch.no_grad():
        before = net(x)
        conv = net.up[-1][0]
        version = conv.weight._version
        conv.weight.data = conv.weight.detach() * 2.0
        assert conv.weight._version == version
        after = net(x)
        torch.testing.assert_close(after, _reference_forward(net, x), rtol=1e-5, atol=2e-6)
    assert not torch.allclose(after, before)


def test_fused_forward_only_after_optimize_for_inference(monkeypatch):
    """no_grad alone runs the plain forward; optimize_for_inference switches to the fused one, whose
    prepacked weights live in the U-Net (a deepcopy starts with an empty cache)."""
    import copy

    calls = []
    original = UNet._forward_fused
    monkeypatch.setattr(UNet, "_forward_fused", lambda self, *a: calls.append(self) or original(self, *a))
    torch.manual_seed(0)
    net = UNet(UNetConfig(in_channels=9, base_channels=4, max_channels=16, norm="affine"), 32).eval()
    x = torch.randn(1, 9, 32, 32)
    with torch.no_grad():
        plain = net(x)
    assert calls == [] and not net.inference_optimized
    assert optimize_for_inference(net) is net and net.inference_optimized
    with torch.no_grad():
        fused = net(x)
    assert calls == [net]
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=2e-6)
    twin = copy.deepcopy(net)
    assert twin.inference_optimized and len(twin._prepacked) == 0
    assert set(twin.state_dict()) == set(net.state_dict())


def test_training_after_optimize_for_inference_matches_plain():
    """Training an optimized model: autograd takes the plain forward (same gradients as an
    unoptimized twin), and inference after the optimizer step uses the new weights."""
    import copy

    torch.manual_seed(0)
    cfg = UNetConfig(in_channels=9, base_channels=4, max_channels=16, norm="batch")
    plain = UNet(cfg, 32)
    net = optimize_for_inference(copy.deepcopy(plain))
    x = torch.randn(2, 9, 32, 32)
    with torch.no_grad():
        net.eval()(x)  # packs the weights
    for m in (plain, net):
        m.train()
        opt = torch.optim.SGD(m.parameters(), lr=0.5)
        m(x).square().mean().backward()
        opt.step()
    for a, b in zip(plain.parameters(), net.parameters()):
        torch.testing.assert_close(a, b)
    net.eval()
    with torch.no_grad():
        torch.testing.assert_close(net(x), _reference_forward(net, x), rtol=1e-5, atol=2e-6)
