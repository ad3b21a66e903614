"""The DELIFFAS model and its ablation variants, composed from one :class:`ModelConfig`.

A frame is rendered in two stages (architecture.md):

1. :meth:`DeliffasModel.encode`: U-Net(s) turn the frame's temporal normal maps into atlas-space
   feature maps (:class:`FrameFeatures`). This depends on the frame only: compute it once and
   reuse it for every camera of that frame.
2. :meth:`DeliffasModel.shade`: per ray, sample the feature maps at the ray's surface uv
   (:func:`deliffas.geometry.sampling.sample_uv`), encode the uv (and the view direction for one
   variant) and evaluate the light-field MLP -> RGB. :meth:`DeliffasModel.shade_chunked` does
   the same in chunks of rays for bounded memory.

Variants (paper section 4.4 and appendix):

=============================  ===========================================  ==================================
variant                        MLP input (encoded)                          features (MLP, after feature_layer)
=============================  ===========================================  ==================================
``single_surface``             PE(uv_inner)                                 inner U-Net @ uv_inner (C)
``single_surface_viewdir``     PE(uv_inner) + PE(viewdir)                   inner U-Net @ uv_inner (C)
``single_surface_two_unet``    PE(uv_inner)                                 two U-Nets on the inner maps @ uv_inner (2C)
``two_surface`` (DELIFFAS)     PE(uv_outer) + PE(uv_inner)                  outer U-Net @ uv_outer, inner U-Net @ uv_inner (2C)
=============================  ===========================================  ==================================

Depth peeling (formats doc 3.4): for rays that miss the inner surface the caller passes the outer
surface's exit-hit uv as ``uv_inner`` and sets ``inner_from_outer``; the "inner" feature of those
rays is then read from the *outer* feature map at that uv. Only ``two_surface`` has an outer map.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import nn

from deliffas.checks import check_shape
from deliffas.models.encoding import PositionalEncoding
from deliffas.models.light_field import LightFieldMLP, LightFieldMLPConfig
from deliffas.geometry.sampling import sample_uv
from deliffas.models.unet import UNet, UNetConfig

__all__ = ["Variant", "VARIANTS", "ModelConfig", "FrameFeatures", "DeliffasModel"]

logger = logging.getLogger(__name__)

Variant = Literal["single_surface", "single_surface_viewdir", "single_surface_two_unet", "two_surface"]
VARIANTS: tuple[str, ...] = ("single_surface", "single_surface_viewdir", "single_surface_two_unet", "two_surface")

#: FLOPs of one bilinear lookup per channel: 4 taps x (multiply + add).
_BILINEAR_FLOPS_PER_CHANNEL = 8


@dataclass(frozen=True)
class ModelConfig:
    """Configuration of :class:`DeliffasModel` (all sizes; nothing here is a path)."""

    variant: Variant = "two_surface"
    """Which model: ``two_surface`` is DELIFFAS; the others are the paper's ablations."""
    atlas_res: int = 1024
    """S: side of the square uv atlas, of the normal maps and of the feature maps."""
    temporal_window: int = 2
    """T: the normal-map window holds frames f, f-1, ..., f-T, so U-Net inputs have 3 (T + 1)
    channels (T = 2 -> 9 channels, as the original's t, t-1, t-2)."""
    unet: UNetConfig | None = None
    """U-Net architecture (shared by all U-Nets of the model). None = ``UNetConfig`` defaults with
    ``in_channels = 3 (T + 1)`` and ``out_channels = feature_channels``; if given, those two
    fields must match."""
    mlp: LightFieldMLPConfig = field(default_factory=LightFieldMLPConfig)
    """Light-field MLP architecture."""
    pe_freqs: int = 10
    """Frequencies of the uv positional encoding (2 + 4 L values per uv; L = 10 -> 42)."""
    viewdir_pe_freqs: int = 4
    """Frequencies of the view-direction encoding (``single_surface_viewdir`` only)."""
    feature_channels: int = 32
    """C: channels of each U-Net's feature map."""

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"ModelConfig: variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.atlas_res < 2:
            raise ValueError(f"ModelConfig: atlas_res must be >= 2, got {self.atlas_res}")
        if self.temporal_window < 0:
            raise ValueError(f"ModelConfig: temporal_window must be >= 0, got {self.temporal_window}")
        if self.pe_freqs < 0 or self.viewdir_pe_freqs < 0:
            raise ValueError(
                f"ModelConfig: pe_freqs and viewdir_pe_freqs must be >= 0, got {self.pe_freqs}, {self.viewdir_pe_freqs}"
            )
        if self.feature_channels < 1:
            raise ValueError(f"ModelConfig: feature_channels must be >= 1, got {self.feature_channels}")
        if self.unet is None:
            object.__setattr__(
                self, "unet", UNetConfig(in_channels=self.input_channels, out_channels=self.feature_channels)
            )
        elif self.unet.in_channels != self.input_channels or self.unet.out_channels != self.feature_channels:
            raise ValueError(
                f"ModelConfig: unet has in_channels={self.unet.in_channels}, out_channels={self.unet.out_channels}; "
                f"temporal_window={self.temporal_window} and feature_channels={self.feature_channels} "
                f"require {self.input_channels} and {self.feature_channels}"
            )

    @property
    def input_channels(self) -> int:
        """Channels of one temporal normal map: 3 (T + 1)."""
        return 3 * (self.temporal_window + 1)

    @property
    def uses_outer_surface(self) -> bool:
        """True for ``two_surface``: needs outer normal maps and ``uv_outer``."""
        return self.variant == "two_surface"

    @property
    def uses_viewdir(self) -> bool:
        """True for ``single_surface_viewdir``: needs per-ray view directions."""
        return self.variant == "single_surface_viewdir"


@dataclass(frozen=True)
class FrameFeatures:
    """Feature maps of one batch of frames; camera-independent (reuse for every camera).

    Attributes:
        inner: (B, C_inner, S, S) float in [0, 1]: the inner U-Net's map (C_inner = C), or both
            inner U-Nets' maps concatenated along channels for ``single_surface_two_unet``
            (C_inner = 2C).
        outer: (B, C, S, S) float in [0, 1], outer U-Net's map; None unless ``two_surface``.

    :meth:`DeliffasModel.encode` stores both in channels_last memory format (texel channels
    adjacent), which makes the per-ray lookups several times faster on large maps.
    """

    inner: torch.Tensor
    outer: torch.Tensor | None = None

    @property
    def batch_size(self) -> int:
        """B, number of frames."""
        return int(self.inner.shape[0])


class DeliffasModel(nn.Module):
    """DELIFFAS (``two_surface``) or one of its ablation variants.

    Args:
        config: the model configuration; every submodule is built from it.

    Attributes:
        unet_inner: U-Net on the inner normal maps.
        unet_inner_2: second U-Net on the inner maps (``single_surface_two_unet`` only, else None).
        unet_outer: U-Net on the outer normal maps (``two_surface`` only, else None).
        pe_uv: uv positional encoding; pe_viewdir: view-direction encoding (viewdir variant only).
        mlp: the light-field MLP.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        unet_cfg = config.unet
        assert unet_cfg is not None  # filled by ModelConfig.__post_init__
        size = config.atlas_res
        self.unet_inner = UNet(unet_cfg, size)
        self.unet_inner_2 = UNet(unet_cfg, size) if config.variant == "single_surface_two_unet" else None
        self.unet_outer = UNet(unet_cfg, size) if config.variant == "two_surface" else None
        self.pe_uv = PositionalEncoding(2, config.pe_freqs)
        self.pe_viewdir = PositionalEncoding(3, config.viewdir_pe_freqs) if config.uses_viewdir else None

        c = config.feature_channels
        if config.variant == "single_surface":
            in_dim, feature_dim = self.pe_uv.out_dim, c
        elif config.variant == "single_surface_viewdir":
            assert self.pe_viewdir is not None
            in_dim, feature_dim = self.pe_uv.out_dim + self.pe_viewdir.out_dim, c
        elif config.variant == "single_surface_two_unet":
            in_dim, feature_dim = self.pe_uv.out_dim, 2 * c
        else:  # two_surface
            in_dim, feature_dim = 2 * self.pe_uv.out_dim, 2 * c
        self.mlp = LightFieldMLP(config.mlp, in_dim, feature_dim)

    # ------------------------------------------------------------------ stage 1: per frame
    def encode(self, normal_inner: torch.Tensor, normal_outer: torch.Tensor | None = None) -> FrameFeatures:
        """Run the U-Net(s) on a batch of temporal normal maps.

        Args:
            normal_inner: (B, 3 (T + 1), S, S) float, inner-surface normals in [-1, 1], frames
                f, f-1, ..., f-T stacked along channels.
            normal_outer: (B, 3 (T + 1), S, S), outer-surface normals; required for
                ``two_surface``, ignored by the single-surface variants.

        Returns:
            The frame's feature maps.
        """
        cfg = self.config
        spec = f"B {cfg.input_channels} {cfg.atlas_res} {cfg.atlas_res}"
        sizes = check_shape("normal_inner", normal_inner, spec)
        inner = self.unet_inner(normal_inner)
        if self.unet_inner_2 is not None:
            inner = torch.cat([inner, self.unet_inner_2(normal_inner)], dim=1)  # (B, 2C, S, S)
        outer = None
        if self.unet_outer is not None:
            if normal_outer is None:
                raise ValueError("encode: normal_outer is required for variant 'two_surface'")
            check_shape("normal_outer", normal_outer, spec, sizes)
            outer = self.unet_outer(normal_outer).contiguous(memory_format=torch.channels_last)
        return FrameFeatures(inner=inner.contiguous(memory_format=torch.channels_last), outer=outer)

    # ------------------------------------------------------------------ stage 2: per ray
    def gather_inputs(
        self,
        features: FrameFeatures,
        batch_index: torch.Tensor,
        uv_inner: torch.Tensor,
        uv_outer: torch.Tensor | None = None,
        viewdir: torch.Tensor | None = None,
        inner_from_outer: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The light-field MLP's inputs for N rays: positional encodings and sampled features.

        Stage 'sample' of the paper's runtime breakdown; :meth:`shade` = ``mlp(*gather_inputs(...))``.

        Args:
            features: the frames' feature maps from :meth:`encode`.
            batch_index: (N,) long, which frame of ``features`` each ray belongs to.
            uv_inner: (N, 2) float in [0, 1]^2, inner-surface hit uv; for rays that miss the
                inner surface, the outer surface's exit (second) hit uv.
            uv_outer: (N, 2) float, outer-surface first-hit uv (``two_surface`` only).
            viewdir: (N, 3) float, unit ray directions, world frame (``single_surface_viewdir`` only).
            inner_from_outer: (N,) bool, True where ``uv_inner`` is an outer exit hit, so the
                inner feature is read from the outer map. None = all False. Only
                ``two_surface`` may have True entries.

        Returns:
            encoded (N, E) positional encodings and feats (N, C') sampled features.
        """
        cfg = self.config
        sizes = check_shape("uv_inner", uv_inner, "N 2")
        check_shape("batch_index", batch_index, "N", sizes)
        if inner_from_outer is not None:
            check_shape("inner_from_outer", inner_from_outer, "N", sizes)
            if inner_from_outer.dtype != torch.bool:
                raise ValueError(f"inner_from_outer: expected dtype bool, got {inner_from_outer.dtype}")

        if cfg.variant == "two_surface":
            if uv_outer is None:
                raise ValueError("shade: uv_outer is required for variant 'two_surface'")
            if features.outer is None:
                raise ValueError("shade: features.outer is None; encode() with normal_outer first")
            check_shape("uv_outer", uv_outer, "N 2", sizes)
            f_outer = sample_uv(features.outer, batch_index, uv_outer)  # (N, C)
            f_inner = self._sample_inner(features, batch_index, uv_inner, inner_from_outer)  # (N, C)
            encoded = torch.cat([self.pe_uv(uv_outer), self.pe_uv(uv_inner)], dim=-1)
            feats = torch.cat([f_outer, f_inner], dim=-1)  # (N, 2C)
            return encoded, feats

        if inner_from_outer is not None and bool(inner_from_outer.any()):
            raise ValueError(
                f"shade: inner_from_outer has True entries but variant {cfg.variant!r} has no outer feature map"
            )
        feats = sample_uv(features.inner, batch_index, uv_inner)  # (N, C) or (N, 2C)
        encoded = self.pe_uv(uv_inner)
        if self.pe_viewdir is not None:
            if viewdir is None:
                raise ValueError("shade: viewdir is required for variant 'single_surface_viewdir'")
            check_shape("viewdir", viewdir, "N 3", sizes)
            encoded = torch.cat([encoded, self.pe_viewdir(viewdir.to(uv_inner.dtype))], dim=-1)
        return encoded, feats

    def shade(
        self,
        features: FrameFeatures,
        batch_index: torch.Tensor,
        uv_inner: torch.Tensor,
        uv_outer: torch.Tensor | None = None,
        viewdir: torch.Tensor | None = None,
        inner_from_outer: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Colour of N rays: (N, 3) RGB in (0, 1). Arguments as :meth:`gather_inputs`."""
        return self.mlp(*self.gather_inputs(features, batch_index, uv_inner, uv_outer, viewdir, inner_from_outer))

    @staticmethod
    def _sample_inner(
        features: FrameFeatures,
        batch_index: torch.Tensor,
        uv_inner: torch.Tensor,
        inner_from_outer: torch.Tensor | None,
    ) -> torch.Tensor:
        """Inner feature per ray, read from the outer map where ``inner_from_outer``: (N, C)."""
        assert features.outer is not None
        if inner_from_outer is None:
            return sample_uv(features.inner, batch_index, uv_inner)
        num_from_outer = int(inner_from_outer.sum())
        if num_from_outer == 0:
            return sample_uv(features.inner, batch_index, uv_inner)
        if num_from_outer == inner_from_outer.numel():
            return sample_uv(features.outer, batch_index, uv_inner)
        idx_o = inner_from_outer.nonzero().squeeze(1)
        idx_i = (~inner_from_outer).nonzero().squeeze(1)
        vals_i = sample_uv(features.inner, batch_index[idx_i], uv_inner[idx_i])
        vals_o = sample_uv(features.outer, batch_index[idx_o], uv_inner[idx_o])
        out = vals_i.new_zeros(uv_inner.shape[0], vals_i.shape[1])
        return out.index_copy(0, idx_i, vals_i).index_copy(0, idx_o, vals_o)

    def shade_chunked(
        self,
        features: FrameFeatures,
        batch_index: torch.Tensor,
        uv_inner: torch.Tensor,
        uv_outer: torch.Tensor | None = None,
        viewdir: torch.Tensor | None = None,
        inner_from_outer: torch.Tensor | None = None,
        chunk_size: int = 65536,
    ) -> torch.Tensor:
        """:meth:`shade` over chunks of ``chunk_size`` rays; same arguments and result.

        Peak activation memory is bounded by the chunk (e.g. a 940 x 1285 frame is ~1.2 M rays).
        Gradients flow as in :meth:`shade`; wrap in ``torch.no_grad()`` for rendering.
        """
        if chunk_size < 1:
            raise ValueError(f"shade_chunked: chunk_size must be >= 1, got {chunk_size}")
        num_rays = uv_inner.shape[0]
        if num_rays <= chunk_size:
            return self.shade(features, batch_index, uv_inner, uv_outer, viewdir, inner_from_outer)
        pieces = []
        for start in range(0, num_rays, chunk_size):
            sl = slice(start, start + chunk_size)
            pieces.append(
                self.shade(
                    features,
                    batch_index[sl],
                    uv_inner[sl],
                    None if uv_outer is None else uv_outer[sl],
                    None if viewdir is None else viewdir[sl],
                    None if inner_from_outer is None else inner_from_outer[sl],
                )
            )
        return torch.cat(pieces, dim=0)

    def forward(
        self,
        normal_inner: torch.Tensor,
        normal_outer: torch.Tensor | None,
        batch_index: torch.Tensor,
        uv_inner: torch.Tensor,
        uv_outer: torch.Tensor | None = None,
        viewdir: torch.Tensor | None = None,
        inner_from_outer: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``shade(encode(normal_inner, normal_outer), ...)``: (N, 3) RGB; see both methods."""
        features = self.encode(normal_inner, normal_outer)
        return self.shade(features, batch_index, uv_inner, uv_outer, viewdir, inner_from_outer)

    # ------------------------------------------------------------------ accounting
    def num_parameters(self, trainable_only: bool = False) -> int:
        """Number of parameter values (all, or only those with ``requires_grad``)."""
        return int(sum(p.numel() for p in self.parameters() if p.requires_grad or not trainable_only))

    def flops_per_ray(self) -> int:
        """Estimated FLOPs per ray of :meth:`shade`.

        Counts the MLP (2 per multiply-add, plus bias adds and ReLUs, see
        :meth:`LightFieldMLP.flops_per_ray`) and the bilinear feature lookups (8 FLOPs per
        channel per lookup). Positional encoding (a few dozen sin/cos) and the sigmoid are not
        counted. The per-frame U-Net cost is independent of the ray count and not included.
        """
        sampled_channels = self.mlp.feature_dim
        return self.mlp.flops_per_ray() + _BILINEAR_FLOPS_PER_CHANNEL * sampled_channels
