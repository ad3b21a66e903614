"""The DELIFFAS model and its ablation variants, composed from one :class:`ModelConfig`.

A frame is rendered in two stages (architecture.md):

1. :meth:`DeliffasModel.encode`: U-Net(s) turn the frame's temporal normal maps into atlas-space
   feature maps (:class:`FrameFeatures`). This depends on the frame only: compute it once and
   reuse it for every camera of that frame.
2. :meth:`DeliffasModel.shade`: per ray (a :class:`~deliffas.models.ray_query.RayQuery`), sample
   the feature maps at the ray's surface uvs (:func:`deliffas.geometry.sampling.sample_uv`),
   encode the uvs (and the view direction where the variant asks) and evaluate the light-field
   MLP -> RGB. :meth:`DeliffasModel.shade_chunked` does the same in chunks of rays for bounded
   memory.

What each variant's U-Nets and MLP take is its :class:`~deliffas.models.variants.VariantSpec`
(``ModelConfig.variant`` names it; the paper's four are in :mod:`deliffas.models.variants`):

=============================  ===========================================  ==================================
variant                        MLP input (encoded)                          features (MLP, after feature_layer)
=============================  ===========================================  ==================================
``single_surface``             PE(uv_inner)                                 inner U-Net @ uv_inner (C)
``single_surface_viewdir``     PE(uv_inner) + PE(viewdir)                   inner U-Net @ uv_inner (C)
``single_surface_two_unet``    PE(uv_inner)                                 two U-Nets on the inner maps @ uv_inner (2C)
``two_surface`` (DELIFFAS)     PE(uv_outer) + PE(uv_inner)                  outer U-Net @ uv_outer, inner U-Net @ uv_inner (2C)
``two_surface_reflect``        PE(uv_outer) + PE(uv_inner) + PE(reflected)  as ``two_surface``
=============================  ===========================================  ==================================

``reflected`` is the view direction reflected about the inner normal at ``uv_inner`` (the current frame's
normal map, carried in :attr:`FrameFeatures.normals`).

Depth peeling (formats doc 3.4): for rays that miss the inner surface the caller passes the outer
surface's exit-hit uv as ``uv_inner`` and sets ``inner_from_outer``; the "inner" feature of those
rays is then read from the *outer* feature map at that uv. Only variants whose spec allows it
(``two_surface``) accept True entries.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from deliffas.checks import check_shape
from deliffas.geometry.sampling import sample_uv
from deliffas.models.encoding import PositionalEncoding, encode_parts
from deliffas.models.light_field import LightFieldMLP, LightFieldMLPConfig
from deliffas.models.ray_query import RayQuery
from deliffas.models.unet import UNet, UNetConfig
from deliffas.models.variants import PAPER_VARIANTS, VariantSpec, get_variant

__all__ = ["VARIANTS", "ModelConfig", "FrameFeatures", "DeliffasModel"]

logger = logging.getLogger(__name__)

VARIANTS: tuple[str, ...] = tuple(spec.name for spec in PAPER_VARIANTS)
"""Names of the paper's four variants (the registry may hold more: ``variants.variant_names()``)."""

#: FLOPs of one bilinear lookup per channel: 4 taps x (multiply + add).
_BILINEAR_FLOPS_PER_CHANNEL = 8


@dataclass(frozen=True)
class ModelConfig:
    """Configuration of :class:`DeliffasModel` (all sizes; nothing here is a path)."""

    variant: str = "two_surface"
    """Name of a registered :class:`~deliffas.models.variants.VariantSpec`: ``two_surface`` is
    DELIFFAS; ``single_surface``, ``single_surface_viewdir``, ``single_surface_two_unet`` the paper's
    ablations."""
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
    """Frequencies of the view-direction encoding (variants with ``viewdir``: ``single_surface_viewdir``,
    ``two_surface_reflect``)."""
    feature_channels: int = 32
    """C: channels of each U-Net's feature map."""
    texture_channels: int = 0
    """C_t: channels of a learnable per-texel feature atlas (S x S, a neural texture) appended to each
    U-Net's feature map (one atlas per map: inner and, with an outer U-Net, outer). It carries the
    appearance that normal maps cannot predict; 0 = none (the paper's model)."""
    texture_scale: int = 1
    """Side of the texture atlases as a multiple of ``atlas_res``. Above 1 they hold finer detail than the
    normal maps: the U-Nets' maps are then upsampled (bilinear) to that side, so every map a ray samples
    has it (with ``unet_downsample`` 1)."""
    unet_downsample: int = 1
    """The U-Nets read the normal maps average-pooled by this factor (a power of two) and write feature maps of
    side S / factor; the texture atlases keep their side, and each map is sampled at its own side (the atlases
    apart, never joined). 2 = a quarter of the U-Nets' per-frame work, the texture atlases keeping the fine
    appearance."""

    def __post_init__(self) -> None:
        try:
            get_variant(self.variant)
        except ValueError as exc:
            raise ValueError(f"ModelConfig: {exc}") from None
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
        if self.texture_channels < 0:
            raise ValueError(f"ModelConfig: texture_channels must be >= 0, got {self.texture_channels}")
        if self.texture_scale < 1:
            raise ValueError(f"ModelConfig: texture_scale must be >= 1, got {self.texture_scale}")
        d = self.unet_downsample
        if d < 1 or d & (d - 1) or self.atlas_res % d or self.atlas_res // d < 2:
            raise ValueError(f"ModelConfig: unet_downsample must be a power of two dividing atlas_res "
                             f"{self.atlas_res} into a side >= 2, got {d}")
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
    def unet_side(self) -> int:
        """Side of the U-Nets' inputs and feature maps: S / ``unet_downsample``."""
        return self.atlas_res // self.unet_downsample

    @property
    def textures_apart(self) -> bool:
        """Whether the texture atlases are always sampled apart from the feature maps (their sides differ)."""
        return self.unet_downsample > 1

    @property
    def spec(self) -> VariantSpec:
        """The registered spec of ``variant``: which U-Nets and per-ray inputs the model uses."""
        return get_variant(self.variant)


@dataclass(frozen=True)
class FrameFeatures:
    """Feature maps of one batch of frames; camera-independent (reuse for every camera).

    Attributes:
        inner: (B, C_inner, S', S') float in [0, 1] (S' = S / ``unet_downsample``): the inner U-Net's map
            (C_inner = C), or the maps of n inner U-Nets concatenated along channels (C_inner = n C, e.g.
            ``single_surface_two_unet``).
        outer: (B, C, S, S) float in [0, 1], outer U-Net's map; None unless the variant has an
            outer U-Net (``two_surface``).
        normals: see below.

    With ``ModelConfig.texture_channels`` = C_t > 0 each map carries C_t more channels: its learnable
    texture atlas, appended after the U-Net channels (same for every frame). ``encode(..., joined=False)``
    (the CPU training step) keeps the atlases apart instead, in ``inner_texture`` / ``outer_texture``, and
    the lookups sample them separately: the same values, without writing the joined maps (and splitting their
    gradient) every step.

    :meth:`DeliffasModel.encode` stores both in channels_last memory format (texel channels
    adjacent), which makes the per-ray lookups several times faster on large maps.
    """

    inner: torch.Tensor
    outer: torch.Tensor | None = None
    normals: torch.Tensor | None = None
    """(B, 3, S, S) the current frame's inner normals (the first three channels of the normal maps), channels_last;
    set by :meth:`DeliffasModel.encode` for variants with ``reflect_viewdir`` only."""
    inner_texture: torch.Tensor | None = None
    """(1, C_t, S_t, S_t) the inner texture atlas, channels_last, where ``inner`` does not carry it."""
    outer_texture: torch.Tensor | None = None
    """(1, C_t, S_t, S_t) the outer texture atlas, channels_last, where ``outer`` does not carry it."""

    def sample(self, surface: Literal["inner", "outer"], batch_index: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """(N, C + C_t) the ``surface``'s features at ``uv`` (:func:`~deliffas.geometry.sampling.sample_uv`),
        its texture atlas's channels last."""
        maps = self.inner if surface == "inner" else self.outer
        texture = self.inner_texture if surface == "inner" else self.outer_texture
        assert maps is not None
        values = sample_uv(maps, batch_index, uv)
        if texture is None:
            return values
        return torch.cat([values, sample_uv(texture, torch.zeros_like(batch_index), uv)], dim=-1)

    @property
    def batch_size(self) -> int:
        """B, number of frames."""
        return int(self.inner.shape[0])


class DeliffasModel(nn.Module):
    """DELIFFAS (``two_surface``) or another registered variant.

    Args:
        config: the model configuration; every submodule is built from it and its variant's spec.

    Attributes:
        spec: the variant's :class:`~deliffas.models.variants.VariantSpec`.
        unet_inner: U-Net on the inner normal maps; ``unet_inner_2`` .. ``unet_inner_<n>`` the
            further inner U-Nets of the spec (``unet_inner_2`` is None when it has one).
        unet_outer: U-Net on the outer normal maps (None unless the spec has one).
        pe_uv: uv positional encoding; pe_viewdir: view-direction encoding (None unless the spec
            feeds the view direction).
        mlp: the light-field MLP.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.spec = spec = config.spec
        unet_cfg = config.unet
        assert unet_cfg is not None  # filled by ModelConfig.__post_init__
        size = config.unet_side
        self.unet_inner = UNet(unet_cfg, size)
        # attribute names unet_inner_2, ... keep the state_dict keys of earlier checkpoints
        self.unet_inner_2 = None
        for i in range(2, spec.inner_unets + 1):
            setattr(self, f"unet_inner_{i}", UNet(unet_cfg, size))
        self.unet_outer = UNet(unet_cfg, size) if spec.outer_unet else None
        ct, side = config.texture_channels, config.texture_scale * config.atlas_res
        # channels-last, the layout the sampler reads and its backward writes: no copy of an atlas or of its
        # gradient per step (the state_dict's values are the same; checkpoints store them contiguous)
        atlas = lambda: nn.Parameter(torch.zeros(1, ct, side, side).contiguous(memory_format=torch.channels_last))  # noqa: E731
        self.texture_inner = atlas() if ct else None
        self.texture_outer = atlas() if ct and spec.outer_unet else None
        self.pe_uv = PositionalEncoding(2, config.pe_freqs)
        self.pe_viewdir = PositionalEncoding(3, config.viewdir_pe_freqs) if spec.viewdir else None
        in_dim = spec.encoded_dim(self.pe_uv.out_dim, self.pe_viewdir.out_dim if self.pe_viewdir else 0)
        maps = 1 + int(spec.outer_unet)
        self.mlp = LightFieldMLP(config.mlp, in_dim, spec.feature_dim(config.feature_channels) + maps * ct)

    def inner_unets(self) -> list[UNet]:
        """The U-Nets on the inner normal maps, in the order their maps are concatenated."""
        return [self.unet_inner] + [getattr(self, f"unet_inner_{i}") for i in range(2, self.spec.inner_unets + 1)]

    def _unets(self) -> list[UNet]:
        return self.inner_unets() + ([self.unet_outer] if self.unet_outer is not None else [])

    def feature_logits(self) -> list[torch.Tensor]:
        """The sigmoid inputs of every U-Net's last forward with autograd on (``UNet.last_logits``)."""
        return [net.last_logits for net in self._unets() if net.last_logits is not None]

    def track_saturation(self, margin: float | None) -> None:
        """Have every U-Net's forward with autograd on compute its saturation penalty at ``margin`` (None: not),
        read by :meth:`feature_penalties`."""
        for net in self._unets():
            net.saturation_margin = margin

    def feature_penalties(self, margin: float) -> list[torch.Tensor] | None:
        """The saturation penalties at ``margin`` of every U-Net's last forward with autograd on
        (``UNet.last_penalty``), or None when one of those forwards did not compute it at that margin."""
        nets = [net for net in self._unets() if net.last_logits is not None]
        if any(net.last_penalty is None or net.saturation_margin != margin for net in nets):
            return None
        return [net.last_penalty for net in nets]

    # ------------------------------------------------------------------ stage 1: per frame
    def encode(self, normal_inner: torch.Tensor, normal_outer: torch.Tensor | None = None, *,
               joined: bool = True) -> FrameFeatures:
        """Run the U-Net(s) on a batch of temporal normal maps.

        Args:
            normal_inner: (B, 3 (T + 1), S, S) float, inner-surface normals in [-1, 1], frames
                f, f-1, ..., f-T stacked along channels.
            normal_outer: (B, 3 (T + 1), S, S), outer-surface normals; required when the
                variant has an outer U-Net, ignored otherwise.
            joined: the texture atlases appended to the maps' channels (for renderers, which sample each
                frame's maps many times); False keeps them apart (``FrameFeatures.inner_texture``: the
                training step, whose maps change every step and are sampled once).

        Returns:
            The frame's feature maps.
        """
        cfg = self.config
        shape = f"B {cfg.input_channels} {cfg.atlas_res} {cfg.atlas_res}"
        sizes = check_shape("normal_inner", normal_inner, shape)
        # finer atlases: the maps upsampled and joined to them; downsampled U-Nets: the atlases always apart
        split = (not joined and cfg.texture_scale == 1) or cfg.textures_apart
        unet_in = self._unet_input(normal_inner)
        maps = [net(unet_in) for net in self.inner_unets()]
        inner = self._with_texture(maps, None if split else self.texture_inner)  # (B, n C [+ C_t], S, S)
        outer = None
        if self.unet_outer is not None:
            if normal_outer is None:
                raise ValueError(f"encode: normal_outer is required for variant {cfg.variant!r}")
            check_shape("normal_outer", normal_outer, shape, sizes)
            outer = self._with_texture([self.unet_outer(self._unet_input(normal_outer))],
                                       None if split else self.texture_outer)
        normals = None
        if self.spec.reflect_viewdir:
            normals = normal_inner[:, :3].contiguous(memory_format=torch.channels_last)
        textures = (self.texture_inner, self.texture_outer) if split else (None, None)
        apart = [None if t is None else t.contiguous(memory_format=torch.channels_last) for t in textures]
        return FrameFeatures(inner=inner, outer=outer, normals=normals, inner_texture=apart[0],
                             outer_texture=apart[1])

    def _unet_input(self, normal_maps: torch.Tensor) -> torch.Tensor:
        """The U-Nets' input: the normal maps average-pooled by ``unet_downsample`` (themselves at 1)."""
        d = self.config.unet_downsample
        return normal_maps if d == 1 else F.avg_pool2d(normal_maps, d)

    @staticmethod
    def _with_texture(maps: list[torch.Tensor], texture: torch.Tensor | None) -> torch.Tensor:
        """The U-Nets' maps (each (B, C, S, S)) and the texture atlas (1, C_t, S_t, S_t), if any, along
        channels, in channels_last memory format; the maps upsampled to S_t first where S_t > S.

        Concatenating the maps' channels-last views writes that format in one pass (and its backward
        reads it in one), instead of a concatenation and a conversion."""
        if texture is not None:
            side = texture.shape[-1]
            if maps[0].shape[-1] != side:
                maps = [F.interpolate(m, size=(side, side), mode="bilinear", align_corners=False) for m in maps]
            maps = [*maps, texture.to(maps[0].dtype).expand(maps[0].shape[0], -1, -1, -1)]
        if len(maps) == 1:
            return maps[0].contiguous(memory_format=torch.channels_last)
        return torch.cat([m.permute(0, 2, 3, 1) for m in maps], dim=3).permute(0, 3, 1, 2)  # channels_last

    def texture_parameters(self) -> list[nn.Parameter]:
        """The texture atlases (empty without ``texture_channels``): the optimiser may give them their own rate."""
        return [t for t in (self.texture_inner, self.texture_outer) if t is not None]

    # ------------------------------------------------------------------ stage 2: per ray
    def gather_inputs(self, features: FrameFeatures, query: RayQuery) -> tuple[torch.Tensor, torch.Tensor]:
        """The light-field MLP's inputs for N rays: positional encodings and sampled features.

        Stage 'sample' of the paper's runtime breakdown; :meth:`shade` = ``mlp(*gather_inputs(...))``.

        Args:
            features: the frames' feature maps from :meth:`encode`.
            query: the rays; the fields the variant's spec reads must be set.

        Returns:
            encoded (N, E) positional encodings and feats (N, C') sampled features.

        Raises:
            ValueError: a field the variant needs is None, or ``inner_from_outer`` has True entries
                for a variant without depth peeling.
        """
        spec, name = self.spec, self.config.variant
        if spec.uses_uv_outer and query.uv_outer is None:
            raise ValueError(f"shade: uv_outer is required for variant {name!r}")
        if spec.viewdir and query.viewdir is None:
            raise ValueError(f"shade: viewdir is required for variant {name!r}")
        peel = query.inner_from_outer
        if not spec.inner_from_outer and peel is not None and bool(peel.any()):
            raise ValueError(f"shade: inner_from_outer has True entries but variant {name!r} has no outer feature map")
        if spec.outer_unet and features.outer is None:
            raise ValueError("shade: features.outer is None; encode() with normal_outer first")
        if spec.inner_from_outer:
            feats = self._sample_peeled(features, query.batch_index, query.uv_outer, query.uv_inner, peel)
        else:
            feats = [features.sample("inner", query.batch_index, query.uv_inner)]  # (N, n C [+ C_t])
            if spec.outer_unet:
                feats.insert(0, features.sample("outer", query.batch_index, query.uv_outer))  # (N, C [+ C_t])
        uvs = {"inner": query.uv_inner, "outer": query.uv_outer}
        encoded = [(uvs[surface], self.pe_uv) for surface in spec.encoded_uvs]
        if self.pe_viewdir is not None:
            viewdir = query.viewdir.to(query.uv_inner.dtype)
            if spec.reflect_viewdir:
                viewdir = self._reflected(features, query, viewdir)
            encoded.append((viewdir, self.pe_viewdir))
        return encode_parts(encoded), feats[0] if len(feats) == 1 else torch.cat(feats, dim=-1)

    @staticmethod
    def _reflected(features: FrameFeatures, query: RayQuery, viewdir: torch.Tensor) -> torch.Tensor:
        """The view directions (N, 3) reflected about the unit inner normals at ``uv_inner``: d - 2 (d . n) n."""
        if features.normals is None:
            raise ValueError("shade: features.normals is None; encode() the frame with this model first")
        # (N, 3), contiguous: the sampled view is transposed, and a row norm over it strides across memory
        n = sample_uv(features.normals, query.batch_index, query.uv_inner).to(viewdir.dtype).contiguous()
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        return viewdir - 2 * (viewdir * n).sum(-1, keepdim=True) * n

    def shade(self, features: FrameFeatures, query: RayQuery) -> torch.Tensor:
        """Colour of N rays: (N, 3) RGB in (0, 1). Arguments as :meth:`gather_inputs`."""
        return self.mlp(*self.gather_inputs(features, query))

    @staticmethod
    def _sample_peeled(
        features: FrameFeatures,
        batch_index: torch.Tensor,
        uv_outer: torch.Tensor,
        uv_inner: torch.Tensor,
        inner_from_outer: torch.Tensor | None,
    ) -> list[torch.Tensor]:
        """Outer and inner features per ray, (N, C) each, the inner one read from the outer map where
        ``inner_from_outer``: the outer map is sampled once, at the outer uvs and the peeled rays' exit
        uvs together, so its backward scatters into one gradient map."""
        assert features.outer is not None
        peeled = None if inner_from_outer is None else inner_from_outer.nonzero().squeeze(1)
        if peeled is None or not len(peeled):
            return [features.sample("outer", batch_index, uv_outer), features.sample("inner", batch_index, uv_inner)]
        n = uv_outer.shape[0]
        both = features.sample("outer", torch.cat([batch_index, batch_index[peeled]]),
                               torch.cat([uv_outer, uv_inner[peeled]]))
        if len(peeled) == n:
            return [both[:n], both[n:]]
        kept = (~inner_from_outer).nonzero().squeeze(1)
        vals = features.sample("inner", batch_index[kept], uv_inner[kept])
        inner = vals.new_zeros(n, vals.shape[1]).index_copy(0, kept, vals).index_copy(0, peeled, both[n:])
        return [both[:n], inner]

    def shade_chunked(self, features: FrameFeatures, query: RayQuery, chunk_size: int = 65536) -> torch.Tensor:
        """:meth:`shade` over chunks of ``chunk_size`` rays; same arguments and result.

        Peak activation memory is bounded by the chunk (e.g. a 940 x 1285 frame is ~1.2 M rays).
        Gradients flow as in :meth:`shade`; wrap in ``torch.no_grad()`` for rendering.
        """
        if chunk_size < 1:
            raise ValueError(f"shade_chunked: chunk_size must be >= 1, got {chunk_size}")
        if query.num_rays <= chunk_size:
            return self.shade(features, query)
        return torch.cat([self.shade(features, part) for part in query.chunks(chunk_size)], dim=0)

    def forward(self, normal_inner: torch.Tensor, normal_outer: torch.Tensor | None, query: RayQuery) -> torch.Tensor:
        """``shade(encode(normal_inner, normal_outer), query)``: (N, 3) RGB; see both methods."""
        return self.shade(self.encode(normal_inner, normal_outer), query)

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
