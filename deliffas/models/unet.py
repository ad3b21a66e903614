"""pix2pix-style U-Net that turns a temporal normal map into an atlas-space feature map.

Architecture (formats doc 3.5, paper appendix "Feature Extractor"):

* ``L`` down blocks: Conv k4 s2 p1 (no bias) -> norm (not on the first block) -> LeakyReLU(0.3,
  the Keras default slope of the original). Channels ``min(base * 2^i, max)``, i = 0 .. L-1.
* ``L - 1`` up blocks: ConvTranspose k4 s2 p1 (no bias) -> norm -> [Dropout 0.5 on the first
  three, off by default] -> ReLU, each followed by concatenation with the mirrored down activation.
* final ConvTranspose k4 s2 p1 to ``out_channels`` -> tanh -> (x + 1) / 2, so features lie in [0, 1].

With ``levels = log2(S)`` the bottleneck is 1 x 1 (10 levels at 1024^2 as in the paper; channels
16, 32, ..., 512, 512, 512, 512, 512). Fewer levels are allowed (bottleneck S / 2^L).

Normalisation (``UNetConfig.norm``):

* ``"batch"``: ``nn.BatchNorm2d`` with batch statistics in training. Batch statistics of a 1 x 1
  map are undefined at batch size 1 (torch raises), so when the innermost down block outputs
  1 x 1 it has no normalisation, as the innermost block of junyanz's PyTorch pix2pix.
* ``"affine"``: a learned per-channel scale and shift in every place BatchNorm would be. This is
  what the released TF code effectively computed: its Keras models are called without a
  ``training`` flag, so BatchNorm ran in inference mode with its initial moving statistics
  (formats doc 3.5, inferred, not executed).
* ``"none"``: no normalisation (all convolutions then get a bias; otherwise only the final one has).

Weights are initialised N(0, 0.02) (conv and transposed conv); norm scales 1, shifts 0.

Speed (CPU): large maps run in channels_last (``CHANNELS_LAST_MIN_PIXELS``), small ones as plain
matrix products (``GEMM_MAX_PIXELS``); the parameters are those of ``nn.Conv2d`` /
``nn.ConvTranspose2d`` (subclasses, same state_dict) and results agree up to float rounding.
Activations are in
place, and outside autograd (``torch.no_grad`` / ``inference_mode``) the affine norm and the final
``(tanh + 1) / 2`` (computed as the identical ``sigmoid(2 x)``) are in place too, so rendering
allocates one map per layer and no temporaries.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["UNetConfig", "UNet", "resolve_levels", "unet_channels"]

logger = logging.getLogger(__name__)

NormKind = Literal["batch", "affine", "none"]

GEMM_MAX_PIXELS = 8 * 8
"""On CPU, every (transposed) convolution whose input has at most this many pixels runs as one
matrix product with the unfolded input (fold after it for the transposed one). These deep
layers are bound by reading their large weights (16-32 MB each at 512 channels), which oneDNN
re-lays out on every call; the product reads them once (1.5-9x faster per layer on this
2-core CPU; at 16 x 16 the two are even)."""

CHANNELS_LAST_MIN_PIXELS = 32 * 32
"""On CPU, every (transposed) convolution whose input has at least this many pixels runs in
channels_last memory format: oneDNN is up to 7x faster there in that layout (e.g. the first
9 -> 16 convolution at 1024^2), while the deep, small maps are faster in the default layout."""


@dataclass(frozen=True)
class UNetConfig:
    """Configuration of :class:`UNet`."""

    in_channels: int
    """Input channels: 3 (T + 1) for a temporal normal map over a window of T + 1 frames."""
    out_channels: int = 32
    """Feature channels of the output map (32 in the paper)."""
    base_channels: int = 16
    """Channels of the first down block; doubled per level up to ``max_channels``."""
    max_channels: int = 512
    """Upper bound on the channels of any block."""
    levels: int | None = None
    """Number of down (and up) sampling stages; None = log2(S), i.e. a 1 x 1 bottleneck."""
    dropout: bool = False
    """Dropout 0.5 after the first three up blocks (pix2pix); off by default (the original ran
    its U-Nets in inference mode, so its dropout was inactive)."""
    norm: NormKind = "batch"
    """Normalisation after every down block but the first and every up block (see module doc)."""
    negative_slope: float = 0.3
    """LeakyReLU slope of the down blocks (Keras default, as the original)."""

    def __post_init__(self) -> None:
        if self.in_channels < 1 or self.out_channels < 1:
            raise ValueError(f"UNetConfig: channels must be >= 1, got in={self.in_channels}, out={self.out_channels}")
        if self.base_channels < 1 or self.max_channels < self.base_channels:
            raise ValueError(
                f"UNetConfig: need 1 <= base_channels <= max_channels, got {self.base_channels}, {self.max_channels}"
            )
        if self.levels is not None and self.levels < 1:
            raise ValueError(f"UNetConfig: levels must be >= 1 or None, got {self.levels}")
        if self.norm not in ("batch", "affine", "none"):
            raise ValueError(f"UNetConfig: norm must be 'batch', 'affine' or 'none', got {self.norm!r}")


def resolve_levels(config: UNetConfig, size: int) -> int:
    """Number of levels of a U-Net on S x S inputs.

    Args:
        config: the U-Net configuration.
        size: S, atlas side.

    Returns:
        ``config.levels`` or, when None, log2(S).

    Raises:
        ValueError: if S is not divisible by 2^levels (or not a power of two when levels is None).
    """
    if size < 2:
        raise ValueError(f"UNet: atlas side must be >= 2, got {size}")
    if config.levels is None:
        levels = int(round(math.log2(size)))
        if 2**levels != size:
            raise ValueError(f"UNet: levels=None needs a power-of-two atlas side, got S={size}")
        return levels
    if size % (2**config.levels) != 0:
        raise ValueError(f"UNet: S={size} is not divisible by 2^levels = {2 ** config.levels}")
    return config.levels


def unet_channels(config: UNetConfig, levels: int) -> list[int]:
    """Output channels of the down blocks, ``min(base * 2^i, max)`` for i = 0 .. levels-1."""
    return [min(config.base_channels * 2**i, config.max_channels) for i in range(levels)]


class _ChannelAffine(nn.Module):
    """Learned per-channel ``x * scale + shift`` (the ``"affine"`` norm)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w, b = self.weight.view(1, -1, 1, 1), self.bias.view(1, -1, 1, 1)
        if torch.is_grad_enabled():
            return x * w + b
        return x.mul_(w).add_(b)  # inference: in place on the conv output it follows (same values)


def _cpu_layout(x: torch.Tensor) -> torch.Tensor:
    """On CPU: ``x`` in channels_last when it is a large map, else in the default layout (a
    channels_last input would make torch copy the large weights of the deep layers to
    channels_last on every call). Elsewhere: ``x`` unchanged."""
    if x.device.type != "cpu":
        return x
    if x.shape[-2] * x.shape[-1] >= CHANNELS_LAST_MIN_PIXELS:
        return x.contiguous(memory_format=torch.channels_last)
    return x.contiguous()


def _gemm_ok(x: torch.Tensor, conv: nn.Module) -> bool:
    """Whether ``conv`` on ``x`` takes the matrix-product path (small CPU maps, plain convolution)."""
    return (
        x.device.type == "cpu"
        and x.dim() == 4
        and x.shape[-2] * x.shape[-1] <= GEMM_MAX_PIXELS
        and conv.groups == 1
        and conv.dilation == (1, 1)
        and conv.padding_mode == "zeros"
        and isinstance(conv.padding, tuple)
    )


class _Conv2d(nn.Conv2d):
    """``nn.Conv2d`` (same parameters, same result up to float rounding) tuned for CPU: large maps
    in channels_last, small maps as one matrix product of the weights with the unfolded input."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not _gemm_ok(x, self):
            return super().forward(_cpu_layout(x))
        b, _, h, w = x.shape
        (kh, kw), (sh, sw), (ph, pw) = self.kernel_size, self.stride, self.padding
        h_out, w_out = (h + 2 * ph - kh) // sh + 1, (w + 2 * pw - kw) // sw + 1
        cols = F.unfold(x, self.kernel_size, padding=self.padding, stride=self.stride)  # (B, C_in kh kw, L)
        y = torch.matmul(self.weight.reshape(self.out_channels, -1), cols)  # (B, C_out, L)
        y = y.reshape(b, self.out_channels, h_out, w_out)
        return y if self.bias is None else y + self.bias.view(1, -1, 1, 1)


class _ConvTranspose2d(nn.ConvTranspose2d):
    """``nn.ConvTranspose2d`` (same parameters, same result up to float rounding) tuned for CPU:
    large maps in channels_last, small maps as one matrix product followed by ``fold`` (col2im)."""

    def forward(self, x: torch.Tensor, output_size: list[int] | None = None) -> torch.Tensor:
        if output_size is not None or self.output_padding != (0, 0) or not _gemm_ok(x, self):
            return super().forward(_cpu_layout(x), output_size)
        b, c_in, h, w = x.shape
        (kh, kw), (sh, sw), (ph, pw) = self.kernel_size, self.stride, self.padding
        h_out, w_out = (h - 1) * sh - 2 * ph + kh, (w - 1) * sw - 2 * pw + kw
        cols = torch.matmul(self.weight.reshape(c_in, -1).t(), x.reshape(b, c_in, h * w))  # (B, C_out kh kw, H W)
        y = F.fold(cols, (h_out, w_out), self.kernel_size, padding=self.padding, stride=self.stride)
        return y if self.bias is None else y + self.bias.view(1, -1, 1, 1)


def _norm(kind: NormKind, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "affine":
        return _ChannelAffine(channels)
    return nn.Identity()


class UNet(nn.Module):
    """pix2pix U-Net: (B, in_channels, S, S) -> (B, out_channels, S, S) in [0, 1].

    Args:
        config: architecture (see :class:`UNetConfig`).
        size: S, the atlas side the network is built for (fixes the level count when
            ``config.levels`` is None and whether the innermost block sees 1 x 1 maps).

    Attributes:
        levels: number of down/up stages.
        channels: output channels of the down blocks.
    """

    def __init__(self, config: UNetConfig, size: int) -> None:
        super().__init__()
        self.config = config
        self.size = int(size)
        self.levels = resolve_levels(config, self.size)
        self.channels = unet_channels(config, self.levels)
        innermost_is_1x1 = self.size // 2**self.levels == 1

        self.down = nn.ModuleList()
        prev = config.in_channels
        for i, ch in enumerate(self.channels):
            use_norm = i > 0 and not (config.norm == "batch" and i == self.levels - 1 and innermost_is_1x1)
            layers: list[nn.Module] = [
                _Conv2d(prev, ch, kernel_size=4, stride=2, padding=1, bias=config.norm == "none")
            ]
            if use_norm:
                layers.append(_norm(config.norm, ch))
            layers.append(nn.LeakyReLU(config.negative_slope, inplace=True))  # on a fresh conv/norm output
            self.down.append(nn.Sequential(*layers))
            prev = ch

        self.up = nn.ModuleList()
        for k, i in enumerate(range(self.levels - 2, -1, -1)):
            ch = self.channels[i]
            layers = [_ConvTranspose2d(prev, ch, kernel_size=4, stride=2, padding=1, bias=config.norm == "none")]
            layers.append(_norm(config.norm, ch))
            if config.dropout and k < 3:
                layers.append(nn.Dropout(0.5))
            layers.append(nn.ReLU(inplace=True))
            self.up.append(nn.Sequential(*layers))
            prev = 2 * ch  # after concatenation with the skip
        self.final = _ConvTranspose2d(prev, config.out_channels, kernel_size=4, stride=2, padding=1, bias=True)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Initialise conv weights N(0, 0.02), biases 0, norm scales 1 and shifts 0."""
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.normal_(m.weight, 0.0, 0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, (nn.BatchNorm2d, _ChannelAffine)):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Encode a temporal normal map.

        Args:
            x: (B, in_channels, H, W) float, H and W divisible by 2^levels (normally H = W = S);
                channels_last memory format is supported.

        Returns:
            (B, out_channels, H, W) features in [0, 1]; in channels_last memory format when
            computed on CPU with H W >= ``CHANNELS_LAST_MIN_PIXELS``.
        """
        if x.dim() != 4 or x.shape[1] != self.config.in_channels:
            raise ValueError(
                f"UNet: x: expected shape (B, {self.config.in_channels}, H, W), got {tuple(x.shape)}"
            )
        step = 2**self.levels
        if x.shape[-2] % step or x.shape[-1] % step:
            raise ValueError(f"UNet: x: H and W must be divisible by 2^levels = {step}, got {tuple(x.shape)}")
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
        x = skips.pop()  # bottleneck (B, C_{L-1}, H / 2^L, W / 2^L)
        for block in self.up:
            x = torch.cat([block(x), skips.pop()], dim=1)  # (B, 2 C_i, H / 2^(i+1), W / 2^(i+1))
        y = self.final(x)
        # (tanh(y) + 1) / 2 == sigmoid(2 y) exactly in real arithmetic (within 1.2e-7 in float32);
        # sigmoid is ~5x cheaper than tanh on CPU and needs one pass less
        if torch.is_grad_enabled():
            return torch.sigmoid(2.0 * y)
        return y.mul_(2.0).sigmoid_()  # inference: in place
