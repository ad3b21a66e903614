"""LPIPS (Zhang et al. 2018, v0.1, VGG): the network and its linear-layer file.

The distance needs the ImageNet VGG-16 (``deliffas.models.vgg``) *and* the lpips package's
``weights/v0.1/vgg.pth`` (keys ``lin0.model.1.weight`` ... ``lin4.model.1.weight``); both are read
only from files the user gives (or the torch hub cache for VGG-16), never downloaded.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import torch
from torch import nn

from deliffas import environment
from deliffas.models.vgg import VGG16Features, read_state_dict

__all__ = ["ENV_LPIPS_WEIGHTS", "LPIPS", "lpips_candidates", "load_lpips_linear_weights"]

#: Environment variable naming the LPIPS v0.1 VGG linear-layer file.
ENV_LPIPS_WEIGHTS = environment.ENV_LPIPS_WEIGHTS
#: LPIPS VGG layers and their channels.
_LPIPS_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
_LPIPS_CHANNELS = (64, 128, 256, 512, 512)


class LPIPS(nn.Module):
    """LPIPS distance (Zhang et al. 2018, v0.1) on a VGG-16 trunk.

    Inputs in [0, 1] are mapped to [-1, 1], shifted/scaled as LPIPS' ``ScalingLayer``, passed
    through VGG-16 (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3); activations are unit-normalised
    over channels, their squared differences weighted per channel (1 x 1 "lin" layers), averaged
    over space and summed over layers.

    Args:
        backbone: VGG-16 trunk (ImageNet weights for real LPIPS).
        channel_weights: five (C_l,) non-negative tensors (the LPIPS v0.1 lin layers), or None
            for uniform weights 1 / C_l (the substitute distance; not LPIPS).
    """

    def __init__(self, backbone: VGG16Features, channel_weights: list[torch.Tensor] | None = None) -> None:
        super().__init__()
        self.backbone = backbone
        for p in self.backbone.parameters():
            p.requires_grad_(False)
        self.backbone.eval()
        if channel_weights is None:
            channel_weights = [torch.full((c,), 1.0 / c) for c in _LPIPS_CHANNELS]
        if len(channel_weights) != len(_LPIPS_CHANNELS) or any(
            w.shape != (c,) for w, c in zip(channel_weights, _LPIPS_CHANNELS)
        ):
            raise ValueError(f"LPIPS: expected channel weights of sizes {_LPIPS_CHANNELS}")
        for i, w in enumerate(channel_weights):
            self.register_buffer(f"lin{i}", w.detach().float().clone())
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Distance per image pair: x, y (B, 3, H, W) in [0, 1] -> (B,)."""
        if x.dim() != 4 or x.shape[1] != 3 or x.shape != y.shape:
            raise ValueError(f"LPIPS: expected two (B, 3, H, W) batches, got {tuple(x.shape)}, {tuple(y.shape)}")
        fx = self.backbone(((2 * x - 1) - self.shift) / self.scale, _LPIPS_LAYERS)
        fy = self.backbone(((2 * y - 1) - self.shift) / self.scale, _LPIPS_LAYERS)
        total = x.new_zeros(x.shape[0])
        for i, name in enumerate(_LPIPS_LAYERS):
            a = fx[name] / (fx[name].pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            b = fy[name] / (fy[name].pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            weighted = ((a - b) ** 2 * getattr(self, f"lin{i}").view(1, -1, 1, 1)).sum(dim=1)  # (B, h, w)
            total = total + weighted.mean(dim=(1, 2))
        return total


def lpips_candidates(path: str | os.PathLike | None) -> list[Path]:
    """Where the LPIPS v0.1 VGG lin layers are looked for, in order: ``path`` alone when given, else
    ``$DELIFFAS_LPIPS_WEIGHTS``, then the installed ``lpips`` package's ``weights/v0.1/vgg.pth``
    (found without importing the package, which needs torchvision)."""
    if path is not None:
        return [Path(path)]
    out = []
    env = environment.weights_file(ENV_LPIPS_WEIGHTS)
    if env:
        out.append(Path(env))
    spec = importlib.util.find_spec("lpips")
    if spec is not None and spec.origin:
        out.append(Path(spec.origin).parent / "weights" / "v0.1" / "vgg.pth")
    return out


def load_lpips_linear_weights(path: str | os.PathLike) -> list[torch.Tensor]:
    """Read LPIPS v0.1 VGG lin layers (``lin{i}.model.1.weight`` of shape (1, C_l, 1, 1)).

    Args:
        path: ``.pth`` (read with ``weights_only=True``) or ``.safetensors`` file.

    Returns:
        Five (C_l,) tensors.

    Raises:
        ValueError: naming the file and key when the layout differs.
    """
    state = read_state_dict(path)
    weights = []
    for i, c in enumerate(_LPIPS_CHANNELS):
        key = f"lin{i}.model.1.weight"
        if key not in state:
            raise ValueError(f"{path}: missing key {key} (expected the lpips v0.1 vgg.pth layout)")
        w = state[key]
        if tuple(w.shape) != (1, c, 1, 1):
            raise ValueError(f"{path}: {key}: expected shape (1, {c}, 1, 1), got {tuple(w.shape)}")
        weights.append(w.reshape(c).float())
    return weights


