"""The light-field MLP (the paper's light slab ``l``): encoded ray coordinates + features -> RGB.

Layout (paper appendix "Light Field MLP"; released code ``Utils/model_main/nerf_model.py``):
``depth`` hidden Linear+ReLU layers of ``width`` channels on the encoded coordinates; right after
hidden layer ``feature_layer`` (0-based) the sampled U-Net features are concatenated *in front*
of the activations; a final Linear to 3 channels and a sigmoid give RGB in (0, 1). The next layer
computes that concatenation's product as two GEMMs on its weight's column blocks, without writing it.

The paper says "8 layers with 256 channels" with the features entering after the "4th layer";
the released code builds ``netdepth`` hidden layers, concatenates after index 4 and ends with
``Dense(3)``; the formats doc (3.6) reads ``netdepth`` = 7 from the configs. Our default
``depth = 8, feature_layer = 4`` follows the paper's count of 256-wide layers; ``depth = 7``
reproduces the released code. Linear weights use Glorot-uniform and zero biases (the Keras
``Dense`` defaults of the original).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import nn

__all__ = ["LightFieldMLPConfig", "LightFieldMLP", "INFERENCE_CHUNK"]

logger = logging.getLogger(__name__)


INFERENCE_CHUNK = 16384
"""Outside autograd, :meth:`LightFieldMLP.forward` evaluates more rays than this in row chunks of
this size (activations of ~16 MB per 256-wide layer instead of ~1 GB for a 940 x 1285 frame);
each row's result is the same."""


@dataclass(frozen=True)
class LightFieldMLPConfig:
    """Configuration of :class:`LightFieldMLP`."""

    depth: int = 8
    """Number of hidden Linear + ReLU layers (the output Linear to RGB comes on top)."""
    width: int = 256
    """Channels of every hidden layer."""
    feature_layer: int = 4
    """0-based index of the hidden layer after which the sampled features are concatenated."""

    def __post_init__(self) -> None:
        if self.depth < 1 or self.width < 1:
            raise ValueError(f"LightFieldMLPConfig: depth and width must be >= 1, got {self.depth}, {self.width}")
        if not 0 <= self.feature_layer < self.depth:
            raise ValueError(
                f"LightFieldMLPConfig: feature_layer must lie in [0, depth={self.depth}), got {self.feature_layer}"
            )


class LightFieldMLP(nn.Module):
    """Light-field MLP: (N, in_dim) encoded coordinates, (N, feature_dim) features -> (N, 3) RGB.

    Args:
        config: depth, width and where the features enter.
        in_dim: size of the concatenated positional encodings.
        feature_dim: size of the concatenated sampled features (32 per U-Net).
    """

    def __init__(self, config: LightFieldMLPConfig, in_dim: int, feature_dim: int) -> None:
        super().__init__()
        if in_dim < 1 or feature_dim < 0:
            raise ValueError(f"LightFieldMLP: need in_dim >= 1, feature_dim >= 0, got {in_dim}, {feature_dim}")
        self.config = config
        self.in_dim = int(in_dim)
        self.feature_dim = int(feature_dim)
        self.hidden = nn.ModuleList()
        prev = self.in_dim
        for i in range(config.depth):
            self.hidden.append(nn.Linear(prev, config.width))
            prev = config.width + (self.feature_dim if i == config.feature_layer else 0)
        self.output = nn.Linear(prev, 3)
        self.activation = nn.ReLU(inplace=True)  # on each Linear's fresh output: autograd-safe, one pass less
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Glorot-uniform weights, zero biases (Keras ``Dense`` defaults)."""
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, encoded: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Evaluate the light field.

        Args:
            encoded: (N, in_dim) positional encodings of the ray's surface coordinates.
            features: (N, feature_dim) sampled U-Net features.

        Returns:
            (N, 3) RGB in (0, 1).
        """
        if encoded.dim() != 2 or encoded.shape[1] != self.in_dim:
            raise ValueError(f"LightFieldMLP: encoded: expected shape (N, {self.in_dim}), got {tuple(encoded.shape)}")
        if features.dim() != 2 or features.shape != (encoded.shape[0], self.feature_dim):
            raise ValueError(
                f"LightFieldMLP: features: expected shape ({encoded.shape[0]}, {self.feature_dim}), "
                f"got {tuple(features.shape)}"
            )
        num_rays = encoded.shape[0]
        if torch.is_grad_enabled() or num_rays <= INFERENCE_CHUNK:
            return self._forward(encoded, features)
        # inference on many rays: row chunks keep every activation cache-sized and reuse memory
        out = encoded.new_empty(num_rays, 3)
        for start in range(0, num_rays, INFERENCE_CHUNK):
            stop = start + INFERENCE_CHUNK
            out[start:stop] = self._forward(encoded[start:stop], features[start:stop])
        return out

    def _forward(self, encoded: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        h, front = encoded, None
        for i, layer in enumerate(self.hidden):
            h = self.activation(_linear_after_cat(layer, front, h))  # (N, width)
            front = features if i == self.config.feature_layer else None
        return _linear_after_cat(self.output, front, h).sigmoid_()  # in place on the fresh output (autograd-safe)

    def flops_per_ray(self) -> int:
        """Floating-point operations of one evaluation: 2 per multiply-add, plus bias and ReLU adds."""
        total = 0
        for layer in [*self.hidden, self.output]:
            total += 2 * layer.in_features * layer.out_features + layer.out_features
        total += self.config.depth * self.config.width  # ReLUs
        return int(total)


def _linear_after_cat(layer: nn.Linear, front: torch.Tensor | None, h: torch.Tensor) -> torch.Tensor:
    """``layer(torch.cat([front, h], -1))`` without writing the concatenation: one GEMM per column block
    of the weight, accumulated in the output (the same sum up to float rounding order)."""
    if front is None or front.shape[1] == 0:
        return layer(h)
    k = front.shape[1]
    return torch.addmm(layer.bias, h, layer.weight[:, k:].t()).addmm_(front, layer.weight[:, :k].t())
