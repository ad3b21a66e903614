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

Speed (CPU): the convolutions are :mod:`deliffas.models.unet_conv`'s layers (subclasses of
``nn.Conv2d`` / ``nn.ConvTranspose2d``, same state_dict, same values up to float rounding). After
:func:`optimize_for_inference`, outside autograd (``torch.no_grad`` / ``inference_mode``) on CPU,
when every norm can be folded (affine, none, BatchNorm in eval mode; dropout inactive),
:meth:`UNet.forward` calls each conv once with its
block's norm and activation as an epilogue (one oneDNN call with prepacked weights), each up block
writes into the first half of its skip concatenation's buffer, and the final ``(tanh + 1) / 2`` is
the identical ``sigmoid(2 x)`` with the factor 2 folded into the weights, and each conv keeps its
weights prepacked for oneDNN in the U-Net's own :class:`~deliffas.models.unet_prepack.PrepackCache`.
The conv modules are still called once per layer with their usual input and output, so forward
hooks see them. Without that call (or with autograd on) the plain forward runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from deliffas.models.feature_sigmoid import sigmoid_with_penalty
from deliffas.models.unet_conv import Conv2d, ConvTranspose2d
from deliffas.models.unet_cpu import CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS, Epilogue, new_map
from deliffas.models.unet_prepack import PrepackCache

__all__ = ["UNetConfig", "UNet", "resolve_levels", "unet_channels", "optimize_for_inference"]

NormKind = Literal["batch", "affine", "none"]

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
    dropout: bool | float = False
    """Dropout after the first three up blocks (pix2pix): True = rate 0.5 (pix2pix), a float = that
    rate in [0, 1); off by default (the original ran its U-Nets in inference mode, so its dropout was
    inactive)."""
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
        if not isinstance(self.dropout, bool) and not (isinstance(self.dropout, (int, float))
                                                       and 0.0 <= self.dropout < 1.0):
            raise ValueError(f"UNetConfig: dropout must be true/false or a rate in [0, 1), got {self.dropout!r}")

    @property
    def dropout_rate(self) -> float:
        """The dropout probability: 0.5 for ``dropout=True`` (pix2pix), 0 for False, else the rate given."""
        if isinstance(self.dropout, bool):
            return 0.5 if self.dropout else 0.0
        return float(self.dropout)


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
                Conv2d(prev, ch, kernel_size=4, stride=2, padding=1, bias=config.norm == "none")
            ]
            if use_norm:
                layers.append(_norm(config.norm, ch))
            layers.append(nn.LeakyReLU(config.negative_slope, inplace=True))  # on a fresh conv/norm output
            self.down.append(nn.Sequential(*layers))
            prev = ch

        self.up = nn.ModuleList()
        for k, i in enumerate(range(self.levels - 2, -1, -1)):
            ch = self.channels[i]
            layers = [ConvTranspose2d(prev, ch, kernel_size=4, stride=2, padding=1, bias=config.norm == "none")]
            layers.append(_norm(config.norm, ch))
            if config.dropout_rate > 0 and k < 3:
                layers.append(nn.Dropout(config.dropout_rate))
            layers.append(nn.ReLU(inplace=True))
            self.up.append(nn.Sequential(*layers))
            prev = 2 * ch  # after concatenation with the skip
        self.final = ConvTranspose2d(prev, config.out_channels, kernel_size=4, stride=2, padding=1, bias=True)
        self._prepacked: PrepackCache | None = None  # set by optimize_for_inference: the fused forward
        self.last_logits: torch.Tensor | None = None
        """(B, out_channels, H, W) the final sigmoid's inputs of the last forward with autograd on
        (None after one without): what :func:`deliffas.models.losses.saturation_penalty` reads."""
        self.saturation_margin: float | None = None
        """When set, a forward with autograd on also computes the saturation penalty of its logits at this
        margin (:attr:`last_penalty`), in the sigmoid's autograd node (:mod:`deliffas.models.feature_sigmoid`)."""
        self.last_penalty: torch.Tensor | None = None
        """() ``mean(relu(|last_logits| - saturation_margin)^2)`` of the last forward with autograd on and a
        ``saturation_margin``, else None."""
        self.reset_parameters()

    @property
    def inference_optimized(self) -> bool:
        """Whether :func:`optimize_for_inference` switched this U-Net to its fused CPU inference forward."""
        return self._prepacked is not None

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
            computed on CPU with H W >= ``unet_cpu.CHANNELS_LAST_MIN_PIXELS``.
        """
        if x.dim() != 4 or x.shape[1] != self.config.in_channels:
            raise ValueError(
                f"UNet: x: expected shape (B, {self.config.in_channels}, H, W), got {tuple(x.shape)}"
            )
        step = 2**self.levels
        if x.shape[-2] % step or x.shape[-1] % step:
            raise ValueError(f"UNet: x: H and W must be divisible by 2^levels = {step}, got {tuple(x.shape)}")
        if self._prepacked is not None and not torch.is_grad_enabled() and x.device.type == "cpu":
            epilogues = self._epilogues()
            if epilogues is not None:
                self.last_logits = self.last_penalty = None
                return self._forward_fused(x, *epilogues)
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
        x = skips.pop()  # bottleneck (B, C_{L-1}, H / 2^L, W / 2^L)
        for block in self.up:
            x = torch.cat([block(x), skips.pop()], dim=1)  # (B, 2 C_i, H / 2^(i+1), W / 2^(i+1))
        # (tanh(y) + 1) / 2 == sigmoid(2 y) exactly in real arithmetic (within 1.2e-7 in float32);
        # sigmoid is ~5x cheaper than tanh on CPU and needs one pass less
        self.last_penalty = None
        if torch.is_grad_enabled():
            self.last_logits = self.final(x, scale=2.0)  # 2 y, the factor in the weights
            if self.saturation_margin is None:
                return torch.sigmoid(self.last_logits)
            features, self.last_penalty = sigmoid_with_penalty(self.last_logits, self.saturation_margin)
            return features
        self.last_logits = None
        return self.final(x).mul_(2.0).sigmoid_()  # inference: in place

    def _epilogues(self) -> tuple[list[Epilogue], list[Epilogue], Epilogue] | None:
        """The norms and activations of every block as conv epilogues, or None when one of them
        cannot be folded (BatchNorm with batch statistics, active dropout)."""
        down, up = [], []
        for block in self.down:
            layers = list(block)  # (slicing an nn.Sequential builds a new module)
            norm = _fold_norm(layers[1:-1])
            if norm is None:
                return None
            scale, shift, sources = norm
            down.append(Epilogue(scale, shift, "leaky_relu", layers[-1].negative_slope, sources))
        for block in self.up:
            norm = _fold_norm(list(block)[1:-1])
            if norm is None:
                return None
            scale, shift, sources = norm
            up.append(Epilogue(scale, shift, "relu", sources=sources))
        # (tanh(y) + 1) / 2 == sigmoid(2 y); the factor 2 is exact in the weights and bias
        return down, up, Epilogue(2.0, None, act="sigmoid")

    def _forward_fused(
        self, x: torch.Tensor, down: list[Epilogue], up: list[Epilogue], final: Epilogue
    ) -> torch.Tensor:
        """Inference forward: every block is one conv call (the conv modules' forward hooks fire
        with their usual input and output) with its norm and activation fused in; each up block
        writes straight into the first half of its skip concatenation."""
        packs = self._prepacked
        skips = []
        for block, epilogue in zip(self.down, down):
            x = block[0](x, epilogue=epilogue, prepacked=packs)
            skips.append(x)
        x = skips.pop()
        for block, epilogue in zip(self.up, up):
            skip = skips.pop()
            c = block[0].out_channels
            h, w = skip.shape[-2:]
            cat = new_map(skip, c + skip.shape[1], h, w, h * w >= CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS)
            block[0](x, epilogue=epilogue, out=cat[:, :c], prepacked=packs)
            cat[:, c:].copy_(skip)
            x = cat
        return self.final(x, epilogue=final, prepacked=packs)


def optimize_for_inference(model: nn.Module) -> nn.Module:
    """Switch every :class:`UNet` in ``model`` to its fused CPU inference forward; returns ``model``.

    Outside autograd on CPU, each U-Net then runs one oneDNN call per layer with its norm and
    activation fused in and its weights prepacked once, in a cache the U-Net holds (the weights
    are packed again when they, the norms or the input size change). Under autograd the plain
    forward runs as before, so training such a model works and packs fresh weights on the next
    inference call; the cache costs about one more copy of the U-Nets' weights.
    """
    for module in model.modules():
        if isinstance(module, UNet) and module._prepacked is None:
            module._prepacked = PrepackCache()
    return model


def _fold_norm(layers) -> tuple[torch.Tensor | None, torch.Tensor | None, tuple] | None:
    """(scale, shift, sources) of the norm among ``layers`` (norm, optional dropout) in inference,
    (None, None, ()) without a norm, None when it depends on the batch (BatchNorm in training mode
    or without running statistics) or dropout is active. ``sources`` are what scale and shift are
    computed from (see :class:`~deliffas.models.unet_cpu.Epilogue`)."""
    scale = shift = None
    sources: tuple = ()
    for m in layers:
        if isinstance(m, nn.Dropout):
            if m.training and m.p > 0:
                return None
        elif isinstance(m, _ChannelAffine):
            scale, shift, sources = m.weight, m.bias, (m.weight, m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            if m.training or m.running_mean is None or m.running_var is None:
                return None
            scale = torch.rsqrt(m.running_var + m.eps)
            if m.weight is not None:
                scale = scale * m.weight
            shift = -m.running_mean * scale
            if m.bias is not None:
                shift = shift + m.bias
            sources = (m.running_mean, m.running_var, m.weight, m.bias, float(m.eps))
        elif not isinstance(m, nn.Identity):
            return None
    return scale, shift, sources
