"""Inference-only shading of many rays: sampling and encoding fused into the MLP's GEMM operands, in fp32 or bf16.

:class:`FastShader` computes what ``DeliffasModel.shade`` computes, outside autograd on CPU:

* one C pass per ray (``deliffas/csrc/ray_inputs.c``) writes the positional encodings of the ray's uvs (and
  direction) and the bilinearly sampled features (``sample_uv``'s convention: texel centres, border clamp) from
  the channels_last feature maps straight into two row-major GEMM operands, in the MLP's dtype.
  The encodings take one sin/cos per coordinate and the double-angle recurrence in float64 for
  the higher frequencies (the same float32 arguments ``positional_encoding`` rounds to, within
  1e-7 of its values);
* the MLP runs as a chain of ``torch.addmm`` into reused row-chunk buffers; the layer after the
  feature concatenation is split into its feature and hidden columns (two products summed), so
  nothing is concatenated.

``dtype=torch.bfloat16`` keeps bf16 copies of the weights (refreshed when a parameter changes) and
runs every product in bf16 with fp32 output (colours in fp32). Use it where the CPU has native
bf16 (:func:`native_bf16`); elsewhere bf16 is several times slower than fp32.

:meth:`FastShader.shade_fused` does all of it in one C pass instead (a tile of rays in the vector lanes: 16
with AVX-512, 8 elsewhere; each colour written straight to its pixel); the engine's fast path uses it by
default. Its hidden layers run in bf16 with native bf16 dot products (AVX512-BF16's ``vdpbf16ps``, fp32
sums) when the shader's dtype is bf16 and the kernel was built with them for this CPU
(:meth:`FastShader.fused_bf16`), else in fp32; encodings, samples, the output layer and its sigmoid are
fp32 either way. With ``pe_table=True`` its fp32 pass takes the first hidden layer's encoded part from
per-coordinate tables (:meth:`FastShader.encoding_table`: four table rows per coordinate instead of the
sin/cos and 2 L + 1 products; about 1e-4 from the exact pass, whose tiles it keeps where a uv lies outside
[0, 1]); the engine's fast path turns it on (``RenderPathConfig.pe_table``). With ``project_features=True``
the fp32 pass samples the feature layer's feature part from maps projected once per frame's features
(:meth:`FastShader.projected_maps`: bilinear sampling commutes with the layer's product, so each ray reads N
projected columns instead of sampling F features and multiplying them by an (F, N) block; within 1e-6 of the
sampled features); the engine's fast path turns it on (``RenderPathConfig.project_features``).

Supported variants: one inner U-Net, with or without a view direction (``two_surface``, ``two_surface_reflect``,
``single_surface``, ``single_surface_viewdir`` and their texture-atlas models); :func:`supports` says so, and callers
use ``DeliffasModel.shade`` otherwise. The direction's encoding is computed per ray in both C passes (the view
direction, or its reflection about the unit normal sampled from ``FrameFeatures.normals`` at ``uv_inner``, peeled
rays too) and multiplied by its columns of the first layer; the encoding table covers the uvs' part only. Without
the C kernel (``DELIFFAS_NATIVE=0``, no compiler) the inputs come from ``DeliffasModel.gather_inputs``.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
import threading

import torch

from deliffas.models.deliffas import DeliffasModel, FrameFeatures
from deliffas.models.ray_query import RayQuery
from deliffas.native import LazyLibrary, header_structs

__all__ = ["FastShader", "supports", "native_bf16", "mlp_dtype", "ROW_CHUNK", "TABLE_NODES", "PROJECTED_MAX_BYTES"]

logger = logging.getLogger(__name__)

TABLE_NODES = 2048
"""Intervals of :meth:`FastShader.encoding_table` on [0, 1] (a power of 2: x * TABLE_NODES is exact in fp32)."""

PROJECTED_MAX_BYTES = 64 * 2**20
"""The most :meth:`FastShader.projected_maps` projects (all maps together); larger ones (the paper preset's 1024^2
texels of 256 columns) sample the features instead."""

ROW_CHUNK = 16384
"""Rays per MLP chunk of the per-stage path (the fastest of 2048 to 65536 rows on the realtime preset)."""


# signatures: fused_shade.h and ray_inputs.h (deliffas.native.declare); their structures (deliffas_fused_shade_args,
# dir_args): deliffas.native.header_structs
_FUSED = LazyLibrary("fused_shade", "fused_shade.c", ("-ffp-contract=fast", "-fno-math-errno", "-fno-trapping-math", "-std=gnu11"),
                     fallback="the per-stage fast path (ray inputs, then the MLP by addmm)")


_KERNEL = LazyLibrary("ray_inputs", "ray_inputs.c", ("-fno-fast-math", "-ffp-contract=off", "-fno-math-errno"),
                      fallback="DeliffasModel.gather_inputs")


@functools.lru_cache(maxsize=1)
def native_bf16() -> bool:
    """Whether this CPU has native bf16 arithmetic (x86 ``avx512_bf16`` / ``amx_bf16``, Arm ``bf16``)."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = f.read()
    except OSError:
        return False
    return any(flag in flags.split() for flag in ("avx512_bf16", "amx_bf16", "bf16"))


def mlp_dtype(name: str = "auto") -> torch.dtype:
    """The MLP's dtype for ``RenderPathConfig.dtype``: ``float32``, ``bfloat16``, or ``auto`` = bf16 where the CPU
    has native bf16 (:func:`native_bf16`), else fp32."""
    resolved = name if name != "auto" else ("bfloat16" if native_bf16() else "float32")
    return torch.bfloat16 if resolved == "bfloat16" else torch.float32


def _lanes(width: int) -> int:
    """A layer width padded to a multiple of 8, as the fused pass lays out its outputs (8 a vector)."""
    return -(-width // 8) * 8


def _bf16_pairs(w: torch.Tensor) -> torch.Tensor:
    """(K, N) fp32 with K even as (K/2, N) int32 words, each the bf16 pair (w[2k, n], w[2k+1, n]) (low half first)."""
    k, n = w.shape
    if k == 0:  # (no feature columns; an empty tensor's strides cannot be viewed as int32)
        return torch.empty(0, n, dtype=torch.int32)
    return w.to(torch.bfloat16).reshape(k // 2, 2, n).transpose(1, 2).contiguous().view(torch.int32).reshape(k // 2, n)


def supports(model: DeliffasModel) -> bool:
    """Whether :class:`FastShader` can shade ``model``'s variant: one inner U-Net, the encoded uvs ``(outer, inner)`` or
    ``(inner,)``, and a view direction (reflected or not) or none (``two_surface``, ``two_surface_reflect``,
    ``single_surface``, ``single_surface_viewdir``)."""
    spec = model.spec
    viewdir_ok = not spec.viewdir or (model.pe_viewdir is not None and model.pe_viewdir.in_dim == 3)
    return (viewdir_ok and spec.inner_unets == 1 and tuple(spec.encoded_uvs) in (("outer", "inner"), ("inner",))
            and (spec.outer_unet or not spec.inner_from_outer) and model.pe_uv.in_dim == 2)


class FastShader:
    """``model.shade`` for inference on CPU, fused and chunked (module docstring).

    Args:
        model: the model (its weights are read on each call; bf16 copies are refreshed when they change).
        dtype: torch.float32 or torch.bfloat16, the dtype of the MLP's products.
        row_chunk: rays per MLP chunk.
        use_kernel: False = torch only (the C passes' plain path; also without a C compiler).
        fused: False = :meth:`shade_fused` runs the per-stage path (inputs, then the MLP).
        pe_table: :meth:`shade_fused`'s fp32 pass takes the first layer's encoded part from per-coordinate tables
            (:meth:`encoding_table`) instead of encoding and multiplying; False = exact.
        project_features: :meth:`shade_fused`'s fp32 pass samples the feature layer's projected maps
            (:meth:`projected_maps`) instead of the features; False = samples the features and multiplies.
    """

    def __init__(self, model: DeliffasModel, dtype: torch.dtype = torch.float32, row_chunk: int = ROW_CHUNK,
                 use_kernel: bool = True, fused: bool = True, pe_table: bool = False,
                 project_features: bool = False) -> None:
        if not supports(model):
            raise ValueError(f"FastShader: variant {model.config.variant!r} is not supported (see deliffas.fast.shade.supports)")
        if dtype not in (torch.float32, torch.bfloat16):
            raise ValueError(f"FastShader: dtype must be float32 or bfloat16, got {dtype}")
        self.model, self.dtype, self.row_chunk, self.use_kernel = model, dtype, int(row_chunk), bool(use_kernel)
        self.fused = bool(fused)
        self.pe_table = bool(pe_table)
        self.project_features = bool(project_features)
        self._projected_lock = threading.Lock()
        self._projected_key: tuple | None = None
        self._projected: tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None] | None = None
        self._projected_features: tuple[torch.Tensor, torch.Tensor | None] | None = None  # the key's tensors, held
        self._table_key: tuple | None = None
        self._table: torch.Tensor | None = None
        self._fused_key: tuple | None = None
        self._fused: tuple[torch.Tensor, torch.Tensor, int] | None = None
        self._weights_key: tuple | None = None
        self._layers: list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]] = []

    # ------------------------------------------------------------------ weights
    def _key(self) -> tuple:
        return tuple((p.data_ptr(), p._version) for p in self.model.mlp.parameters())

    def layers(self) -> list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]]:
        """Per Linear: (W_h^T (in, out), W_f^T (F, out) or None, bias (out,)) in the MLP's dtype; the output layer
        as (W (3, in), None, bias (3,)) in fp32 (colours from fp32 logits; W untransposed, the layout both its
        kernel and torch's fp32 product with out = 3 want: the transposed copy is several times slower).

        W_f^T is the feature columns of the layer after the concatenation (features come first)."""
        key = self._key()
        if key != self._weights_key:
            mlp = self.model.mlp
            out = []
            for i, lin in enumerate(mlp.hidden):
                w, w_f = lin.weight.detach(), None
                if i == mlp.config.feature_layer + 1 and mlp.feature_dim:
                    w_f, w = w[:, : mlp.feature_dim], w[:, mlp.feature_dim:]
                    w_f = w_f.t().contiguous().to(self.dtype)
                out.append((w.t().contiguous().to(self.dtype), w_f, lin.bias.detach().to(self.dtype).contiguous()))
            last = mlp.output
            out.append((last.weight.detach().float().contiguous(), None, last.bias.detach().float().contiguous()))
            self._layers, self._weights_key = out, key
        return self._layers

    # ------------------------------------------------------------------ inputs
    def _ray_args(self, features: FrameFeatures, query: RayQuery, textures: bool = False) -> tuple[dict, list] | None:
        """The per-ray arguments of the C passes by their C names, in deliffas_ray_inputs' order (uv_in .. dir; fields
        of deliffas_fused_shade_args too), and the tensors they point into (keep them alive); None when the C passes
        cannot read these inputs (several frames, non-fp32 maps, texture atlases apart from the maps unless
        ``textures``: then the fused pass's ``tex_in``, ``tex_out``, ``St``, ``Ct`` follow)."""
        model = self.model
        single = features.batch_size == 1 and (query.batch_index.numel() == 0 or not bool(query.batch_index.any()))
        apart = features.inner_texture is not None
        if not single or features.inner.dtype != torch.float32 or (apart and not textures):
            return None
        spec = model.spec
        maps = [m.permute(0, 2, 3, 1).contiguous() if m is not None else None for m in (features.inner, features.outer)]
        map_in, map_out = maps[0], (maps[1] if spec.outer_unet else None)
        if spec.outer_unet and map_out is None:
            raise ValueError("shade: features.outer is None; encode() with normal_outer first")
        uv_in = query.uv_inner.float().contiguous()
        uv_out = query.uv_outer.float().contiguous() if query.uv_outer is not None else uv_in
        peel = query.inner_from_outer
        if peel is not None and not spec.inner_from_outer and bool(peel.any()):
            raise ValueError(f"shade: inner_from_outer has True entries but variant {model.config.variant!r} has no outer feature map")
        peel_u8 = peel.to(torch.uint8).contiguous() if peel is not None and spec.inner_from_outer else None
        direction = self._direction(features, query)
        if direction is False:
            return None
        S, C = map_in.shape[1], map_in.shape[3]
        args = dict(uv_in=uv_in.data_ptr(), from_outer=peel_u8.data_ptr() if peel_u8 is not None else None,
                    uv_out=uv_out.data_ptr(), outer_encoded=int(spec.encoded_uvs[0] == "outer"),
                    L=model.pe_uv.num_freqs, include_input=int(model.pe_uv.include_input), map_in=map_in.data_ptr(),
                    map_out=map_out.data_ptr() if map_out is not None else None, S=S, C=C,
                    dir=ctypes.addressof(direction[0]) if direction is not None else None)
        held = [uv_in, uv_out, peel_u8, map_in, map_out, direction]
        if textures:
            tex = [t.permute(0, 2, 3, 1).contiguous().float() if t is not None else None
                   for t in (features.inner_texture, features.outer_texture if spec.outer_unet else None)]
            args.update(tex_in=tex[0].data_ptr() if tex[0] is not None else None,
                        tex_out=tex[1].data_ptr() if tex[1] is not None else None,
                        St=int(tex[0].shape[1]) if tex[0] is not None else 0,
                        Ct=int(tex[0].shape[3]) if tex[0] is not None else 0)
            held += tex
        return args, held

    def _direction(self, features: FrameFeatures, query: RayQuery) -> tuple | None | bool:
        """The C passes' ``dir_args`` and the tensors it points into, None for variants without a view direction, False
        where the C passes cannot read them (non-fp32 normal maps)."""
        model, spec = self.model, self.model.spec
        if not spec.viewdir:
            return None
        pe = model.pe_viewdir
        assert pe is not None  # (a variant with a view direction has its encoding)
        if query.viewdir is None:
            raise ValueError(f"shade: viewdir is required for variant {model.config.variant!r}")
        viewdir = query.viewdir.float().contiguous()
        normals = None
        if spec.reflect_viewdir:
            if features.normals is None:
                raise ValueError("shade: features.normals is None; encode() the frame with this model first")
            if features.normals.dtype != torch.float32:
                return False
            normals = features.normals.permute(0, 2, 3, 1).contiguous()  # (1, S, S, 3)
        dir_args = header_structs(_KERNEL.header)["dir_args"]  # ray_inputs.h's
        args = dir_args(viewdir=viewdir.data_ptr(), normals=normals.data_ptr() if normals is not None else None,
                        S=int(normals.shape[1]) if normals is not None else 0, L=pe.num_freqs,
                        include_input=int(pe.include_input))
        return args, viewdir, normals

    def inputs(self, features: FrameFeatures, query: RayQuery) -> tuple[torch.Tensor, torch.Tensor]:
        """The MLP's operands: encoded (N, E) and feats (N, F) in the shader's dtype (C kernel, else torch)."""
        model, n = self.model, query.num_rays
        lib = _KERNEL.get() if self.use_kernel else None
        got = self._ray_args(features, query) if lib is not None else None
        if got is None:
            enc, feats = model.gather_inputs(features, query)
            return enc.to(self.dtype), feats.to(self.dtype).contiguous()
        E, F = model.mlp.in_dim, model.mlp.feature_dim
        enc = torch.empty(n, E, dtype=self.dtype)
        feats = torch.empty(n, F, dtype=self.dtype)
        lib.deliffas_ray_inputs(0, n, *got[0].values(), int(self.dtype == torch.bfloat16), enc.data_ptr(), E,
                                feats.data_ptr(), F)
        return enc, feats

    # ------------------------------------------------------------------ fused
    def _fused_params(self, bf16: bool) -> tuple[torch.Tensor, torch.Tensor, int]:
        """The MLP for the fused pass: (dims (5 nh + 2,) int64, params as 4-byte words, widest hidden layer); hidden
        widths padded to multiples of 8 with zero columns (their ReLU outputs are 0 and meet zero rows downstream).

        fp32: every weight and bias fp32. ``bf16``: the hidden layers' W and Wf as bf16 row pairs (K/2, N, 2) (an odd
        K padded with a zero row), dims giving K/2 and F/2; biases and the output layer fp32."""
        key = (self._key(), bf16)
        if self._fused_key != key:
            mlp = self.model.mlp
            dims, parts, offset, k_in = [], [], 0, mlp.in_dim
            for i, lin in enumerate(mlp.hidden):
                w = lin.weight.detach().float()
                f = mlp.feature_dim if (i == mlp.config.feature_layer + 1 and mlp.feature_dim) else 0
                w_f, w_h = w[:, :f], w[:, f:]
                n_out = _lanes(w.shape[0])
                pad = lambda t, rows: torch.nn.functional.pad(t, (0, n_out - t.shape[1], 0, rows - t.shape[0]))  # noqa: E731
                bias = pad(lin.bias.detach().float()[None], 1).view(torch.int32)
                if bf16:
                    k2, f2 = -(-k_in // 2), -(-f // 2)
                    block = [_bf16_pairs(pad(w_h.t(), 2 * k2)), _bf16_pairs(pad(w_f.t(), 2 * f2)), bias]
                    dims += [k2, n_out, f2, offset, offset + k2 * n_out]
                else:
                    block = [pad(w_h.t(), k_in).view(torch.int32), pad(w_f.t(), f).view(torch.int32), bias]
                    dims += [k_in, n_out, f, offset, offset + k_in * n_out]
                parts += [b.reshape(-1) for b in block]
                offset += sum(b.numel() for b in block)
                k_in = n_out
            w_o = torch.nn.functional.pad(mlp.output.weight.detach().float(), (0, k_in - mlp.output.in_features))
            dims += [offset, k_in]
            parts += [w_o.reshape(-1).view(torch.int32), mlp.output.bias.detach().float().view(torch.int32)]
            widest = max([dims[5 * i + 1] for i in range(len(mlp.hidden))] + [1])
            self._fused = (torch.tensor(dims, dtype=torch.int64), torch.cat(parts).contiguous(), widest)
            self._fused_key = key
        return self._fused

    def encoding_table(self) -> torch.Tensor | None:
        """The first hidden layer's encoded part as per-coordinate tables for :meth:`shade_fused` (``pe_table``).

        The layer adds ``W_e PE(uv)`` to its bias; the encoding treats each coordinate x on its own (x, then sin and
        cos of 2^k pi x), so that sum is ``sum_c g_c(x_c)`` over the 2 or 4 encoded coordinates, with ``g_c`` a fixed
        function of one variable into the layer's width. Tabled at ``TABLE_NODES + 1`` nodes on [0, 1] with its
        derivative, a cubic Hermite interpolation replaces 2 L + 1 products per coordinate by four table rows; its
        error is about ``(2^(L-1) pi / TABLE_NODES)^4 / 384`` of the highest frequency's weights (6e-5 for L = 10).

        Returns (2 nuv, TABLE_NODES + 1, 2, N) float32, N the layer's width padded to 8 (g, then g' / TABLE_NODES),
        rebuilt when the weights change; None when the table does not apply (no hidden layer, or an encoded
        width other than 2 or 4 coordinates' encodings and the view direction's). The view direction's columns are
        not tabled: the pass encodes the direction and multiplies them."""
        key = self._key()
        if key == self._table_key:
            return self._table
        model, mlp = self.model, self.model.mlp
        pe = model.pe_uv
        per_uv = pe.out_dim  # one uv's encoding: (u, v) if included, then sin and cos of both per frequency
        nuv = len(model.spec.encoded_uvs)
        per_dir = model.pe_viewdir.out_dim if model.pe_viewdir is not None else 0  # (multiplied by the pass)
        table = None
        if mlp.hidden and nuv in (1, 2) and mlp.in_dim == nuv * per_uv + per_dir:
            lin = mlp.hidden[0]
            f = mlp.feature_dim if mlp.config.feature_layer + 1 == 0 else 0
            w = lin.weight.detach().to(torch.float64)[:, f:]  # (N, E): the encoded columns
            n_out = _lanes(w.shape[0])
            x = torch.arange(TABLE_NODES + 1, dtype=torch.float64) / TABLE_NODES  # (T + 1,)
            table = torch.zeros(2 * nuv, TABLE_NODES + 1, 2, n_out, dtype=torch.float64)
            for u in range(nuv):
                for d in range(2):
                    base, g, dg = u * per_uv, table[2 * u + d, :, 0, : w.shape[0]], table[2 * u + d, :, 1, : w.shape[0]]
                    if pe.include_input:
                        g += x[:, None] * w[:, base + d]
                        dg += w[:, base + d]
                    first = base + (2 if pe.include_input else 0)
                    for k in range(pe.num_freqs):
                        freq = math.pi * 2.0**k
                        ws, wc = w[:, first + 4 * k + d], w[:, first + 4 * k + 2 + d]
                        sn, cs = torch.sin(freq * x)[:, None], torch.cos(freq * x)[:, None]
                        g += sn * ws + cs * wc
                        dg += freq * (cs * ws - sn * wc)
            table[:, :, 1] /= TABLE_NODES
            table = table.float().contiguous()
        self._table, self._table_key = table, key
        return table

    def projected_maps(self, features: FrameFeatures) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor | None] | None:
        """The feature layer's feature part as maps for :meth:`shade_fused` (``project_features``).

        The layer after the concatenation adds ``Wf_o f_o + Wf_i f_i`` (the outer sample at uv_outer, then the inner
        one at uv_inner); a bilinear sample is a weighted sum of texels, so it commutes with the product:
        ``Wf_i sample(map_in, uv) = sample(map_in Wf_i^T, uv)``. With the maps projected once per frame's features
        (per pose: every camera shares them), each ray samples N columns and skips the F N products.

        Returns (outer map x Wf_o^T or None, inner map x Wf_i^T, outer map x Wf_i^T for peeled rays or None), each
        (S, S, N) float32, N the layer's width padded to 8; cached for the last features (held, so the key stays
        unique) and weights. None when nothing is to project (no feature columns, several frames, non-fp32 maps)
        or the maps would exceed :data:`PROJECTED_MAX_BYTES`."""
        mlp, spec = self.model.mlp, self.model.spec
        inner, outer = features.inner, features.outer if spec.outer_unet else None
        if not mlp.feature_dim or features.batch_size != 1 or inner.dtype != torch.float32 \
                or features.inner_texture is not None:  # (atlases apart: not projected)
            return None
        S, C = int(inner.shape[2]), int(inner.shape[1])
        n_out = _lanes(mlp.hidden[mlp.config.feature_layer + 1].out_features)
        count = (outer is not None) + 1 + (outer is not None and spec.inner_from_outer)
        if count * S * S * n_out * 4 > PROJECTED_MAX_BYTES:
            return None
        key = (self._key(), id(inner), inner._version, id(outer), outer._version if outer is not None else None)
        with self._projected_lock:
            if self._projected_key == key:
                return self._projected
            w = mlp.hidden[mlp.config.feature_layer + 1].weight.detach().float()[:, : mlp.feature_dim]
            w = torch.nn.functional.pad(w, (0, 0, 0, n_out - w.shape[0]))  # (N, F), zero rows for padded outputs
            w_o, w_i = (w[:, :C], w[:, C:]) if outer is not None else (None, w)

            def project(m: torch.Tensor, wt: torch.Tensor) -> torch.Tensor:
                return (m[0].permute(1, 2, 0).reshape(S * S, C) @ wt.t()).reshape(S, S, n_out).contiguous()

            maps = (project(outer, w_o) if outer is not None else None, project(inner, w_i),
                    project(outer, w_i) if outer is not None and spec.inner_from_outer else None)
            # the key holds the features' ids: keep them alive so no other tensor takes their id
            self._projected, self._projected_key, self._projected_features = maps, key, (inner, outer)
            return maps

    def fused_bf16(self) -> bool:
        """Whether :meth:`shade_fused` runs its hidden layers in bf16: the shader's dtype is bf16 and the fused kernel
        was built with native bf16 dot products (AVX512-BF16) this CPU has; else the pass is fp32."""
        lib = _FUSED.get() if self.fused and self.use_kernel and self.dtype == torch.bfloat16 else None
        return lib is not None and bool(lib.deliffas_fused_bf16())

    def fused_available(self) -> bool:
        """Whether :meth:`shade_fused` runs its C pass (``fused=True`` and the kernel built)."""
        return self.fused and self.use_kernel and _FUSED.get() is not None

    def shade_fused(self, features: FrameFeatures, query: RayQuery, out: torch.Tensor | None = None,
                    rows: torch.Tensor | None = None) -> torch.Tensor:
        """``mlp(*inputs(...), out, rows)`` in one C pass, the hidden layers in bf16 where :meth:`fused_bf16`, else
        fp32 (module docstring); the per-stage path where the pass is unavailable or cannot read the inputs."""
        lib = _FUSED.get() if self.fused and self.use_kernel else None
        got = self._ray_args(features, query, textures=True) if lib is not None else None
        if got is None:
            return self.mlp(*self.inputs(features, query), out=out, rows=rows)
        n = query.num_rays
        out, rows = self._check_out(n, out, rows)
        bf16 = self.fused_bf16()
        dims, params, widest = self._fused_params(bf16)
        table = self.encoding_table() if self.pe_table and not bf16 else None
        projected = self.projected_maps(features) if self.project_features and not bf16 else None
        projected = projected if projected is not None else (None, None, None)
        mlp = self.model.mlp
        ptr = lambda t: t.data_ptr() if t is not None else None  # noqa: E731
        proj_out, proj_in, proj_peel = map(ptr, projected)
        args = header_structs(_FUSED.header)["deliffas_fused_shade_args"](  # every field by name (fused_shade.h)
            n=n, **got[0], nh=len(mlp.hidden), dims=dims.data_ptr(), params=params.data_ptr(), E=mlp.in_dim,
            Fd=mlp.feature_dim, wmax=widest, pixels=ptr(rows), out=out.data_ptr(), bf16=int(bf16), pe_table=ptr(table),
            table_nodes=TABLE_NODES, proj_out=proj_out, proj_in=proj_in, proj_peel=proj_peel)
        status = lib.deliffas_fused_shade(ctypes.byref(args))
        if status == -2:
            raise ValueError(f"FastShader.shade_fused: at most 512 feature channels per map, got {features.inner.shape[1]}")
        if status != 0:
            raise MemoryError("FastShader.shade_fused: the scratch tiles could not be allocated")
        return out

    @staticmethod
    def _check_out(n: int, out: torch.Tensor | None, rows: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        if out is None:
            return torch.empty(n, 3, dtype=torch.float32), None
        if rows is None or rows.shape != (n,) or rows.dtype != torch.int64 or out.dtype != torch.float32 \
                or out.dim() != 2 or out.shape[1] != 3 or not out.is_contiguous():
            raise ValueError("FastShader: out must be a contiguous (P, 3) float32 canvas and rows (N,) int64")
        return out, rows.contiguous()

    # ------------------------------------------------------------------ MLP
    def mlp(self, enc: torch.Tensor, feats: torch.Tensor, out: torch.Tensor | None = None,
            rows: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3) float32 RGB of the operands from :meth:`inputs`; or, with ``out`` (P, 3) float32 and ``rows`` (N,)
        int64, ray i's colour written to ``out[rows[i]]`` (an image canvas) and ``out`` returned.

        Hidden layers: ``addmm`` into two buffers reused across row chunks; the output layer, its sigmoid
        and the write: one C pass in fp32 (``use_kernel=False`` or no kernel: torch's fp32 product)."""
        layers = self.layers()
        hidden, (w_out, _, b_out) = layers[:-1], layers[-1]
        n = enc.shape[0]
        out, rows = self._check_out(n, out, rows)
        lib = _KERNEL.get() if self.use_kernel else None
        chunk = min(self.row_chunk, max(n, 1))
        widths = [w_h.shape[1] for w_h, _, _ in hidden]
        bufs = [torch.empty(chunk, max(widths), dtype=self.dtype) for _ in range(2)]
        rows_c = rows
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            h = enc[start:start + m]
            f = feats[start:start + m]
            for i, (w_h, w_f, bias) in enumerate(hidden):
                y = bufs[i % 2][:m, : w_h.shape[1]]
                torch.addmm(bias, h, w_h, out=y)
                if w_f is not None:
                    y.addmm_(f, w_f)
                h = y.relu_()
            if lib is not None:
                lib.deliffas_rgb_out(m, h.data_ptr(), h.stride(0), int(h.dtype == torch.bfloat16), h.shape[1],
                                     w_out.data_ptr(), b_out.data_ptr(),
                                     rows_c[start:].data_ptr() if rows_c is not None else None,
                                     out.data_ptr() if rows_c is not None else out[start:].data_ptr())
            else:
                rgb = torch.addmm(b_out, h.float(), w_out.t()).sigmoid_()
                if rows_c is None:
                    out[start:start + m] = rgb
                else:
                    out.index_copy_(0, rows_c[start:start + m], rgb)
        return out

    @torch.no_grad()
    def shade(self, features: FrameFeatures, query: RayQuery) -> torch.Tensor:
        """(N, 3) float32 RGB in (0, 1): ``model.shade(features, query)`` within the dtype's precision."""
        return self.mlp(*self.inputs(features, query))
