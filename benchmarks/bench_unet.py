"""U-Net stage: achieved FLOP/s of the feature-extractor U-Net against one large convolution.

FLOPs are counted from the layer shapes of the actual forward pass (forward hooks on every
``Conv2d`` and ``ConvTranspose2d``: 2 x multiply-adds; norms, activations and concatenations not
counted). Networks (fp32, batch 1, 9 input channels, 32 output channels, affine norm as the
presets): the paper widths (16 -> 512, log2 S levels) and the ``small`` preset widths (8 -> 64)
at S = 256, and the paper network itself (paper widths at S = 1024, 10 levels).

Baseline, same run, same dtype: one 3x3 conv2d 64 -> 64 at 256^2 (padding 1, no bias), a
large, well-shaped convolution, timed interleaved with every U-Net; all ratios use its best time
over the whole module. Target: U-Net FLOP/s >= 0.50 x that. Smoke mode: S = 32, 32 and 64, the convolution
at 32^2.
"""

from __future__ import annotations

import torch
from torch import nn

from benchmarks._timing import best_times, torch_threads
from benchmarks.common import Result, sized

GROUP = "unet"
TARGET = 0.50
CASES = (("paper", 256, 4), ("small", 256, 4), ("paper", 1024, 2))
"""(widths, S, timed rounds) of the measured U-Nets."""
SMOKE_CASES = (("paper", 32, 1), ("small", 32, 1), ("paper", 64, 1))
CONV_SIDE = 256
"""Side of the baseline convolution's input (smoke mode: 32)."""


def conv_flops(model: nn.Module, x: torch.Tensor) -> int:
    """2 x multiply-adds of every (transposed) convolution in one forward of ``model`` on ``x``."""
    total = 0

    def hook(module: nn.Module, inputs, output) -> None:
        nonlocal total
        k = module.kernel_size[0] * module.kernel_size[1]
        if isinstance(module, nn.ConvTranspose2d):  # every input value meets k x C_out weights
            macs = inputs[0].numel() * module.out_channels * k // module.groups
        else:  # every output value sums k x C_in / groups products
            macs = output.numel() * module.in_channels * k // module.groups
        total += 2 * macs

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))]
    try:
        with torch.inference_mode():
            model(x)
    finally:
        for h in handles:
            h.remove()
    return total


def _unet(preset: str, size: int):
    from deliffas.models.unet import UNet, UNetConfig, optimize_for_inference

    if preset == "paper":
        cfg = UNetConfig(in_channels=9, out_channels=32, norm="affine")
    else:
        cfg = UNetConfig(in_channels=9, out_channels=32, base_channels=8, max_channels=64, norm="affine")
    torch.manual_seed(0)
    return optimize_for_inference(UNet(cfg, size).eval())


def run() -> list[Result]:
    with torch_threads():
        return _run()


def _run() -> list[Result]:
    gen = torch.Generator().manual_seed(0)
    conv = nn.Conv2d(64, 64, 3, padding=1, bias=False).eval()
    side = sized(CONV_SIDE, 32)
    xc = torch.rand(1, 64, side, side, generator=gen)
    conv_fl = 2 * side * side * 64 * 64 * 9
    with torch.inference_mode():
        t_conv = best_times({"conv": lambda: conv(xc)}, repeat=5, min_time=2.0, max_rounds=30)["conv"]
    rows = []
    for preset, size, repeat in sized(CASES, SMOKE_CASES):
        net = _unet(preset, size)
        x = torch.rand(1, 9, size, size, generator=gen) * 2 - 1  # normals in [-1, 1]
        flops = conv_flops(net, x)
        with torch.inference_mode():
            t = best_times({"unet": lambda: net(x), "conv": lambda: conv(xc)}, repeat=repeat, min_time=4.0, max_rounds=30)
        t_conv = min(t_conv, t["conv"])
        rows.append((preset, size, net.levels, flops, t["unet"]))
    # every ratio uses the best convolution time of the whole module (the strictest reference)
    reference = conv_fl / t_conv / 1e9
    results = []
    for preset, size, levels, flops, t_unet in rows:
        achieved = flops / t_unet / 1e9
        ratio = achieved / reference
        results.append(Result(
            GROUP, f"{preset} widths S={size} ({levels} levels), fp32", achieved, "GFLOP/s",
            baseline=f"3x3 conv 64->64 at {side}^2, fp32", ratio=ratio, target=f">= {TARGET:.2f}",
            passed=ratio >= TARGET,
            note=f"{flops / 1e9:.2f} GFLOP in {t_unet * 1e3:.1f} ms; conv {reference:.1f} GFLOP/s ({t_conv * 1e3:.1f} ms)",
        ))  # fmt: skip
    return results
