"""The model of a web export: which variants the player renders, and the U-Nets and MLP as padded arrays.

The player (``player/unet.js``, ``player/shade.js``) keeps every feature map as RGBA float textures, four
channels per texel, so every channel count is padded to a multiple of four here: a layer's input is a list of
segments (the skip concatenation of an up block is two), each padded on its own. A U-Net is a list of
operations, each a 4 x 4 stride-2 convolution (``conv``) or transposed convolution (``convT``) with its norm
folded into a per-channel ``scale`` and ``shift`` after the bias and one activation (``leaky``, ``relu`` or
``sigmoid``). Weights are stored for the shader's ``mat4`` products: ``[g_out, g_in, tap, j, o]`` with tap =
ky * 4 + kx, j the input and o the output channel within their groups of four.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from deliffas.engine.web.bundle import Bundle
from deliffas.models.deliffas import DeliffasModel, ModelConfig
from deliffas.models.unet import UNet
from deliffas.models.variants import VariantSpec, get_variant, variant_names

__all__ = ["web_supported", "supported_variants", "check_web_supported", "pack_model"]


def _ceil4(n: int) -> int:
    return (n + 3) // 4 * 4


def web_supported(spec: VariantSpec) -> bool:
    """Whether the player renders ``spec``: one inner U-Net (an outer one, the view direction, its reflection,
    depth peeling and any encoded uvs allowed)."""
    return spec.inner_unets == 1


def supported_variants() -> tuple[str, ...]:
    """The registered variants the player renders."""
    return tuple(n for n in variant_names() if web_supported(get_variant(n)))


def check_web_supported(config: ModelConfig) -> None:
    """Refuse a model the player cannot render (ValueError naming the supported variants)."""
    if not web_supported(config.spec):
        raise ValueError(f"--web: the web player does not render variant {config.variant!r} (more than one inner "
                         f"U-Net); supported variants: {', '.join(supported_variants())}")
    if config.texture_scale != 1:
        raise ValueError(f"--web: the web player renders texture atlases at the atlas side only (texture_scale 1), "
                         f"this model has texture_scale {config.texture_scale}")


def _padded_input(weight: np.ndarray, segments: list[int]) -> np.ndarray:
    """(O, I, ...) -> (O, sum of padded segments, ...): each input segment's channels at its padded offset."""
    out = np.zeros((weight.shape[0], sum(_ceil4(s) for s in segments), *weight.shape[2:]), np.float32)
    src = dst = 0
    for s in segments:
        out[:, dst:dst + s] = weight[:, src:src + s]
        src, dst = src + s, dst + _ceil4(s)
    return out


def _fold(layers: list[nn.Module], channels: int) -> tuple[np.ndarray, np.ndarray]:
    """(scale, shift) of the norm among ``layers`` in inference (ones and zeros without one)."""
    scale, shift = np.ones(channels), np.zeros(channels)
    for m in layers:
        if isinstance(m, nn.BatchNorm2d):
            s = 1.0 / np.sqrt(m.running_var.double().numpy() + m.eps)
            if m.weight is not None:
                s = s * m.weight.detach().double().numpy()
            shift = -m.running_mean.double().numpy() * s + (0 if m.bias is None else m.bias.detach().double().numpy())
            scale = s
        elif hasattr(m, "weight") and hasattr(m, "bias") and not isinstance(m, nn.Dropout):
            scale, shift = m.weight.detach().double().numpy(), m.bias.detach().double().numpy()
    return scale, shift


def _op(bundle: Bundle, name: str, conv: nn.Module, transposed: bool, segments: list[int], act: str,
        slope: float, scale: np.ndarray, shift: np.ndarray) -> dict:
    """One layer's entry: padded weights and the folded bias, scale and shift."""
    w = conv.weight.detach().double().numpy()
    w = w.transpose(1, 0, 2, 3) if transposed else w  # (O, I, 4, 4)
    cout = w.shape[0]
    bias = np.zeros(cout) if conv.bias is None else conv.bias.detach().double().numpy()
    w = _padded_input(w, segments)
    gin, gout = w.shape[1] // 4, _ceil4(cout) // 4
    full = np.zeros((gout * 4, w.shape[1], 4, 4), np.float32)
    full[:cout] = w
    # [g_out, o, g_in, j, ky, kx] -> [g_out, g_in, ky, kx, j, o]
    packed = full.reshape(gout, 4, gin, 4, 4, 4).transpose(0, 2, 4, 5, 3, 1)
    post = np.zeros((2, gout * 4), np.float32)
    post[0, :cout] = scale
    post[1, :cout] = bias * scale + shift
    return {"kind": "convT" if transposed else "conv", "in_groups": gin, "out_groups": gout, "channels": cout,
            "act": act, "slope": float(slope), "weights": bundle.add(f"{name}.w", packed.reshape(gout * gin, 64 * 4)),
            "post": bundle.add(f"{name}.post", post)}


def _pack_unet(net: UNet, bundle: Bundle, name: str) -> dict:
    """A U-Net as its list of operations; ``skip`` names the down operation whose output an up block's is
    concatenated with."""
    ops, segments = [], [net.config.in_channels]
    for i, block in enumerate(net.down):
        layers = list(block)
        scale, shift = _fold(layers[1:-1], layers[0].out_channels)
        ops.append(_op(bundle, f"{name}.down{i}", layers[0], False, segments, "leaky", layers[-1].negative_slope,
                       scale, shift))
        segments = [layers[0].out_channels]
    for k, block in enumerate(net.up):
        layers = list(block)
        scale, shift = _fold(layers[1:-1], layers[0].out_channels)
        op = _op(bundle, f"{name}.up{k}", layers[0], True, segments, "relu", 0.0, scale, shift)
        op["skip"] = net.levels - 2 - k  # the down block of the same size
        ops.append(op)
        segments = [layers[0].out_channels, layers[0].out_channels]
    out = net.final.out_channels
    # (tanh(y) + 1) / 2 = sigmoid(2 y): scale 2 on the conv and its bias
    ops.append(_op(bundle, f"{name}.final", net.final, True, segments, "sigmoid", 0.0, np.full(out, 2.0),
                   np.zeros(out)))
    return {"levels": net.levels, "in_channels": net.config.in_channels, "ops": ops}


def _pack_mlp(model: DeliffasModel, bundle: Bundle) -> dict:
    """The MLP's layers as rows of padded weights followed by the bias: row (layer, o) = [w (in_p), b, 0, 0, 0],
    each layer's rows padded to a multiple of four with zero rows."""
    mlp, cfg = model.mlp, model.config.mlp
    layers = [*mlp.hidden, mlp.output]
    widths, rows = [], []
    for i, layer in enumerate(layers):
        w = layer.weight.detach().double().numpy()
        front = mlp.feature_dim if i == cfg.feature_layer + 1 else 0
        segments = [front, w.shape[1] - front] if front else [w.shape[1]]
        padded = _padded_input(w, segments)
        widths.append({"in": padded.shape[1], "out": w.shape[0], "front": _ceil4(front)})
        rows.append((padded, layer.bias.detach().double().numpy()))
    width = max(w["in"] for w in widths) + 4
    table = np.zeros((sum(_ceil4(w["out"]) for w in widths), width), np.float32)
    r = 0
    for (w, b), info in zip(rows, widths):
        table[r:r + len(w), :w.shape[1]] = w
        table[r:r + len(w), w.shape[1]] = b
        info["row"] = r
        r += _ceil4(len(w))  # whole groups of four rows: the shader reads four outputs at once
    return {"depth": cfg.depth, "width": cfg.width, "feature_layer": cfg.feature_layer, "in_dim": mlp.in_dim,
            "feature_dim": mlp.feature_dim, "layers": widths, "table": bundle.add("mlp.table", table)}


def _texture(param: torch.Tensor | None, bundle: Bundle, name: str) -> dict | None:
    """A texture atlas (1, C_t, S, S) as (ceil(C_t / 4), S, S, 4): groups of four channels per texel."""
    if param is None:
        return None
    t = param.detach().float().numpy()[0]
    c = t.shape[0]
    t = np.concatenate([t, np.zeros((_ceil4(c) - c, *t.shape[1:]), np.float32)])
    groups = t.reshape(-1, 4, *t.shape[1:]).transpose(0, 2, 3, 1)
    return {"channels": c, "data": bundle.add(name, groups)}


def pack_model(model: DeliffasModel, bundle: Bundle) -> dict:
    """The model's JSON entry, its arrays added to ``bundle`` (ValueError for a model the player cannot render)."""
    cfg = model.config
    check_web_supported(cfg)
    spec = cfg.spec
    # unet_downsample d: the U-Nets run on the normal maps pooled to S / d and their maps are sampled at that side
    return {"variant": cfg.variant, "atlas_res": cfg.atlas_res, "unet_downsample": cfg.unet_downsample,
            "temporal_window": cfg.temporal_window, "feature_channels": cfg.feature_channels,
            "texture_channels": cfg.texture_channels,
            "pe_freqs": cfg.pe_freqs, "viewdir_pe_freqs": cfg.viewdir_pe_freqs,
            "spec": {"outer_unet": spec.outer_unet, "viewdir": spec.viewdir, "reflect_viewdir": spec.reflect_viewdir,
                     "encoded_uvs": list(spec.encoded_uvs), "inner_from_outer": spec.inner_from_outer},
            "unet_inner": _pack_unet(model.unet_inner, bundle, "unet_inner"),
            "unet_outer": None if model.unet_outer is None else _pack_unet(model.unet_outer, bundle, "unet_outer"),
            "texture_inner": _texture(model.texture_inner, bundle, "texture_inner"),
            "texture_outer": _texture(model.texture_outer, bundle, "texture_outer"),
            "mlp": _pack_mlp(model, bundle)}
