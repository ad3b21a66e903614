"""The U-Net's convolution layers and their CPU inference paths.

``Conv2d`` and ``ConvTranspose2d`` are ``nn.Conv2d`` / ``nn.ConvTranspose2d`` with the same
parameters and state_dict, computing the same values up to float rounding, tuned for CPU: large
maps in channels_last, small maps as plain matrix products. Outside autograd they also take an
:class:`Epilogue` (the block's norm, folded into the weights, and its activation, fused into
oneDNN's kernel) and, for transposed convolutions, an ``out`` buffer (the first half of a skip
concatenation), and with a :class:`PrepackCache` (held by the U-Net after
``optimize_for_inference``) :func:`_packed_conv` keeps each module's folded weights in oneDNN's
blocked layout until they change. On other devices the layers are plain torch.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import weakref
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from deliffas.native import LazyLibrary

logger = logging.getLogger(__name__)

GEMM_MAX_PIXELS = 8 * 8
"""On CPU, every transposed convolution whose input has at most this many pixels runs as one
matrix product with the input followed by ``fold`` (col2im). These deep layers are bound by
reading their large weights (16-32 MB each at 512 channels), which oneDNN re-lays out on every
call; the product reads them once (1.5-9x faster per layer on this 2-core CPU)."""

CONV_GEMM_MAX_PIXELS = 16 * 16
"""The same for convolutions (one matrix product with the unfolded input): 1.2-1.7x faster
than oneDNN up to 16 x 16 inputs here (e.g. 128 -> 256 channels at 16^2: 1.7 against 2.1 ms)."""

CHANNELS_LAST_MIN_PIXELS = 32 * 32
"""On CPU, every convolution whose input has at least this many pixels runs in channels_last
memory format: oneDNN is up to 7x faster there in that layout (e.g. the first 9 -> 16
convolution at 1024^2), while the deep, small maps are faster in the default layout."""

CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS = 16 * 16
"""The same for transposed convolutions, which are faster in channels_last from 16 x 16 inputs
on (256 -> 64 channels at 16^2: 1.9 against 2.4 ms)."""


@dataclass(frozen=True)
class Epilogue:
    """Per-channel ``act(y * scale + shift)`` fused into a convolution outside autograd.

    ``scale`` and ``shift`` are (C_out,) tensors (or a float scale) or None; ``act`` is None,
    ``"relu"``, ``"leaky_relu"`` (slope ``slope``) or ``"sigmoid"``. ``sources`` are the tensors
    (and numbers) that tensor-valued ``scale`` and ``shift`` are computed from, e.g. a norm's
    parameters and running statistics: prepacked weights stay valid while these are the same
    objects at the same version (:func:`_packed_conv`), which is cheaper than comparing values."""

    scale: torch.Tensor | float | None = None
    shift: torch.Tensor | None = None
    act: str | None = None
    slope: float = 0.0
    sources: tuple = ()

    def __post_init__(self) -> None:
        if (isinstance(self.scale, torch.Tensor) or isinstance(self.shift, torch.Tensor)) and not self.sources:
            raise ValueError("Epilogue: tensor scale/shift need the sources they are computed from")

    def apply_(self, y: torch.Tensor) -> torch.Tensor:
        """The epilogue in place on ``y`` (a fresh convolution output)."""
        if self.scale is not None:
            y.mul_(self.scale.view(1, -1, 1, 1) if isinstance(self.scale, torch.Tensor) else self.scale)
        if self.shift is not None:
            y.add_(self.shift.view(1, -1, 1, 1))
        return self.activate_(y)

    def activate_(self, y: torch.Tensor) -> torch.Tensor:
        if self.act == "relu":
            y.relu_()
        elif self.act == "leaky_relu":
            F.leaky_relu_(y, self.slope)
        elif self.act == "sigmoid":
            y.sigmoid_()
        elif self.act is not None:
            raise ValueError(f"Epilogue: unknown activation {self.act!r}")
        return y

    def folded(
        self, weight: torch.Tensor, bias: torch.Tensor | None, out_dim: int
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(weight * scale, bias * scale + shift)`` with the scale along ``weight``'s dim ``out_dim``
        (fresh tensors when they differ from the inputs); the convolution then computes
        ``y * scale + shift`` up to float rounding."""
        scale, shift = self.scale, self.shift
        if scale is not None:
            if isinstance(scale, torch.Tensor):
                shape = [1] * weight.dim()
                shape[out_dim] = -1
                weight = weight * scale.view(shape)
            else:
                weight = weight * scale
            if bias is not None:
                bias = bias * scale
        if shift is not None:
            bias = shift if bias is None else bias + shift
        return weight, bias


def _cpu_layout(x: torch.Tensor, min_pixels: int | None = None) -> torch.Tensor:
    """On CPU: ``x`` in channels_last when it has at least ``min_pixels`` pixels (default
    ``CHANNELS_LAST_MIN_PIXELS``), else in the default layout (a channels_last input would make
    torch copy the large weights of the deep layers to channels_last on every call). Elsewhere:
    ``x`` unchanged."""
    if x.device.type != "cpu":
        return x
    if x.shape[-2] * x.shape[-1] >= (CHANNELS_LAST_MIN_PIXELS if min_pixels is None else min_pixels):
        return channels_last(x)
    return x.contiguous()


# dst[n][p][c] = src[n][c][p] for float32: N maps of C planes of P pixels to channels_last order.
# Loops specialised for the U-Net's usual 3 (T + 1) input channels (gcc vectorises them), a
# pixel-blocked loop otherwise. Exact copies: no arithmetic.
_LAYOUT_SOURCE = r"""
#include <stdint.h>
#define INTERLEAVE(C) \
    static void interleave_##C(const float *restrict src, float *restrict dst, int64_t pixels) { \
        for (int64_t p = 0; p < pixels; p++) \
            for (int c = 0; c < C; c++) dst[p * C + c] = src[c * pixels + p]; \
    }
INTERLEAVE(3)
INTERLEAVE(6)
INTERLEAVE(9)
INTERLEAVE(12)

static void interleave_any(const float *restrict src, float *restrict dst, int64_t channels, int64_t pixels) {
    const int64_t block = 64;
    for (int64_t p0 = 0; p0 < pixels; p0 += block) {
        int64_t n = pixels - p0 < block ? pixels - p0 : block;
        for (int64_t c = 0; c < channels; c++) {
            const float *s = src + c * pixels + p0;
            float *d = dst + p0 * channels + c;
            for (int64_t p = 0; p < n; p++) d[p * channels] = s[p];
        }
    }
}

void deliffas_planar_to_interleaved_f32(const float *src, float *dst, int64_t batch, int64_t channels,
                                        int64_t pixels) {
    for (int64_t n = 0; n < batch; n++) {
        const float *s = src + n * channels * pixels;
        float *d = dst + n * channels * pixels;
        switch (channels) {
            case 3: interleave_3(s, d, pixels); break;
            case 6: interleave_6(s, d, pixels); break;
            case 9: interleave_9(s, d, pixels); break;
            case 12: interleave_12(s, d, pixels); break;
            default: interleave_any(s, d, channels, pixels);
        }
    }
}
"""


def _declare_layout(lib: ctypes.CDLL) -> None:
    i64 = ctypes.c_int64
    lib.deliffas_planar_to_interleaved_f32.argtypes = [ctypes.c_void_p, ctypes.c_void_p, i64, i64, i64]
    lib.deliffas_planar_to_interleaved_f32.restype = None


_LAYOUT_KERNEL = LazyLibrary("unet_layout", _LAYOUT_SOURCE, setup=_declare_layout,
                             fallback="torch's channels_last copy for the U-Net input, about 2x slower")


def channels_last(x: torch.Tensor) -> torch.Tensor:
    """``x`` (N, C, H, W) in channels_last memory format (``x`` itself when it already is).

    A dense float32 CPU map in the default layout (the U-Net's input) is converted by a compiled
    loop into a fresh :func:`new_map`: 0.12 against 0.32 ms for torch's copy at 9 x 256^2, 3.7
    against 5.8 ms at 9 x 1024^2, the same values. Other inputs, inputs that autograd tracks, or
    without a C compiler (or with ``DELIFFAS_NATIVE=0``, see :mod:`deliffas.native`), use torch's
    copy."""
    if x.is_contiguous(memory_format=torch.channels_last):
        return x
    no_grad = not (x.requires_grad and torch.is_grad_enabled())  # the compiled copy has no backward
    if no_grad and x.device.type == "cpu" and x.dtype == torch.float32 and x.dim() == 4 and x.is_contiguous():
        lib = _LAYOUT_KERNEL.get()
        if lib is not None:
            n, c, h, w = x.shape
            out = new_map(x, c, h, w, channels_last=True)
            lib.deliffas_planar_to_interleaved_f32(x.data_ptr(), out.data_ptr(), n, c, h * w)
            return out
    return x.contiguous(memory_format=torch.channels_last)


HUGE_PAGE_MIN_BYTES = 4 << 20
"""Fresh CPU maps of at least this size that the U-Net allocates itself (skip concatenations, the
channels_last copy of the input) are advised to the kernel as transparent huge pages (Linux
``madvise(MADV_HUGEPAGE)``; a no-op elsewhere or when THP is disabled). Their pages are touched
first by the U-Net's own writes, which otherwise fault in one 4 kB page at a time: on this VM a
fault costs ~2.5 us, ~40 ms for the 64 MB concatenation before the last layer of the paper U-Net
at 1024^2."""

_MADV_HUGEPAGE = 14
_HUGE_PAGE = 2 << 20
_madvise = None


def _advise_huge_pages(t: torch.Tensor) -> torch.Tensor:
    """Advise the 2 MB-aligned pages inside ``t``'s (fresh, untouched) memory as huge pages."""
    global _madvise
    nbytes = t.numel() * t.element_size()
    if t.device.type != "cpu" or nbytes < HUGE_PAGE_MIN_BYTES or not sys.platform.startswith("linux"):
        return t
    if _madvise is None:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
            libc.madvise.restype = ctypes.c_int
            _madvise = libc.madvise
        except (OSError, AttributeError):
            _madvise = False
    if _madvise:
        start = -(-t.data_ptr() // _HUGE_PAGE) * _HUGE_PAGE
        end = (t.data_ptr() + nbytes) // _HUGE_PAGE * _HUGE_PAGE
        if end > start:
            _madvise(start, end - start, _MADV_HUGEPAGE)  # advice only: failure changes nothing
    return t


def new_map(
    like: torch.Tensor, channels: int, height: int, width: int, channels_last: bool | None = None
) -> torch.Tensor:
    """Uninitialised (B, channels, height, width) map on ``like``'s device and dtype, in the
    layout :func:`_cpu_layout` gives a map of that size (or channels_last if asked), advised as
    huge pages when large."""
    if channels_last is None:
        channels_last = height * width >= CHANNELS_LAST_MIN_PIXELS
    b = like.shape[0]
    numel, item = b * channels * height * width, like.element_size()
    if like.device.type != "cpu" or numel * item < HUGE_PAGE_MIN_BYTES:
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        return torch.empty((b, channels, height, width), dtype=like.dtype, device=like.device, memory_format=fmt)
    # one flat buffer with 2 MB of slack, used from its first 2 MB boundary on: every page of the map
    # can then be a huge page
    flat = torch.empty(numel + _HUGE_PAGE // item, dtype=like.dtype, device=like.device)
    start = (-flat.data_ptr() % _HUGE_PAGE) // item
    flat = _advise_huge_pages(flat[start : start + numel])
    if channels_last:
        return flat.view(b, height, width, channels).permute(0, 3, 1, 2)
    return flat.view(b, channels, height, width)


def _gemm_ok(x: torch.Tensor, conv: nn.Module) -> bool:
    """Whether ``conv`` on ``x`` takes the matrix-product path (small CPU maps, plain convolution)."""
    max_pixels = GEMM_MAX_PIXELS if isinstance(conv, nn.ConvTranspose2d) else CONV_GEMM_MAX_PIXELS
    return (
        x.device.type == "cpu"
        and x.dim() == 4
        and x.shape[-2] * x.shape[-1] <= max_pixels
        and conv.groups == 1
        and conv.dilation == (1, 1)
        and conv.padding_mode == "zeros"
        and isinstance(conv.padding, tuple)
    )


def _finish(y: torch.Tensor, epilogue: Epilogue | None, out: torch.Tensor | None) -> torch.Tensor:
    """Apply ``epilogue`` in place on the fresh output ``y``, then copy it into ``out`` if given."""
    if epilogue is not None:
        epilogue.apply_(y)
    if out is None:
        return y
    out.copy_(y)
    return out


def _check_fused(epilogue: Epilogue | None, out: torch.Tensor | None) -> None:
    if (epilogue is not None or out is not None) and torch.is_grad_enabled():
        raise RuntimeError("U-Net conv: epilogue/out are for inference only (torch.no_grad / inference_mode)")


_onednn_pointwise_ok = True

_ONEDNN_ATTR = {"relu": "relu", "leaky_relu": "leaky_relu", "sigmoid": "sigmoid", None: "none"}


def _onednn_attr(epilogue: Epilogue) -> tuple[str, list]:
    """oneDNN's post-op name and scalars for the epilogue's activation (one of ``_ONEDNN_ATTR``)."""
    return _ONEDNN_ATTR[epilogue.act], [epilogue.slope] if epilogue.act == "leaky_relu" else []


def _onednn_act(
    transposed: bool,
    x: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    epilogue: Epilogue,
    padding: tuple[int, int],
    stride: tuple[int, int] = (1, 1),
    dilation: tuple[int, int] = (1, 1),
    groups: int = 1,
    output_padding: tuple[int, int] = (0, 0),
) -> torch.Tensor | None:
    """``act(conv(x, weight, bias))`` (``conv_transpose2d`` if ``transposed``) with the epilogue's
    activation applied inside oneDNN's kernel while each output tile is in cache: one pass less
    over the output. These are torch's ``mkldnn._convolution[_transpose]_pointwise`` ops, which
    torch.compile fuses to on CPU. None when they are missing or refuse the arguments (the caller
    then activates separately)."""
    global _onednn_pointwise_ok
    if (not _onednn_pointwise_ok or epilogue.act is None or epilogue.act not in _ONEDNN_ATTR
            or x.device.type != "cpu" or x.dtype != torch.float32):
        return None
    name, scalars = _onednn_attr(epilogue)
    try:
        if transposed:
            return torch.ops.mkldnn._convolution_transpose_pointwise(
                x, weight, bias, list(padding), list(output_padding), list(stride), list(dilation), groups, name,
                scalars, "",
            )
        return torch.ops.mkldnn._convolution_pointwise(
            x, weight, bias, list(padding), list(stride), list(dilation), groups, name, scalars, ""
        )
    except (AttributeError, RuntimeError, NotImplementedError) as exc:
        _onednn_pointwise_ok = False
        logger.info("unet: oneDNN fused convolution + activation unavailable (%s); activating separately", exc)
        return None


def _pack_key(conv: nn.Module, epilogue: Epilogue, x: torch.Tensor) -> tuple[tuple, tuple]:
    """(items, states) that prepacked weights of ``conv`` for ``epilogue`` and ``x`` derive from:
    the conv's weight and bias, the epilogue's sources and constants, the input shape. Items are
    compared by identity (the entry keeps them alive, so an identity cannot be reused); states by
    value: each tensor item's version counter (in-place changes) and data pointer (``.data``
    assignments, which keep both identity and version), non-tensor items as they are."""
    items = (conv.weight, conv.bias, *epilogue.sources)
    scale = epilogue.scale
    states = [x.shape, epilogue.act, epilogue.slope, None if isinstance(scale, torch.Tensor) else scale,
              epilogue.shift is None]
    for t in items:
        if isinstance(t, torch.Tensor):
            # inference tensors have no version counter: a fresh object() never matches
            states.append(object() if t.is_inference() else t._version)
            states.append(t.data_ptr())
        else:
            states.append(t)
    return items, tuple(states)


@dataclass(frozen=True)
class _PackedWeights:
    """Folded convolution weights in oneDNN's blocked layout, what they were built from, and the
    form of the computation (see :func:`_narrow_form`)."""

    items: tuple
    states: tuple
    form: str
    """"direct" (conv), "transposed" (transposed conv), "column_pairs" or "phases"."""
    weight: torch.Tensor
    """oneDNN (mkldnn) tensor: ``weight * scale`` in the form's shape, reordered for the input shape."""
    bias: torch.Tensor | None
    """``bias * scale + shift`` (dense, repeated as the form needs), or None."""
    padding: list[int]
    stride: list[int]
    dilation: list[int]
    output_padding: list[int]
    attr: str
    scalars: list

    def matches(self, items: tuple, states: tuple) -> bool:
        # states hold at least one entry per item, so equal states mean equally many items
        return states == self.states and all(a is b for a, b in zip(items, self.items))

    def __call__(self, x: torch.Tensor, out: torch.Tensor | None) -> torch.Tensor:
        if self.form == "transposed":
            y = torch.ops.mkldnn._convolution_transpose_pointwise(
                x, self.weight, self.bias, self.padding, self.output_padding, self.stride, self.dilation, 1, self.attr,
                self.scalars, "",
            )  # fmt: skip
        else:
            y = torch.ops.mkldnn._convolution_pointwise(
                x, self.weight, self.bias, self.padding, self.stride, self.dilation, 1, self.attr, self.scalars, ""
            )
        if self.form == "phases":
            n, c4, h1, w1 = y.shape
            if out is None:
                out = new_map(y, c4 // 4, 2 * (h1 - 1), 2 * (w1 - 1), channels_last=True)
            return _interleave_phases(y, out)
        if self.form == "column_pairs":
            y = _merge_column_pairs(y)
        return _finish(y, None, out)


class PrepackCache:
    """Per conv module of one U-Net, its last prepacked weights; the U-Net holds it (see
    ``deliffas.models.unet.optimize_for_inference``), so nothing is cached for the process. One
    entry per module, about the size of its weights. It is state, not a parameter: state_dict
    never sees it, and a copy (deepcopy, pickling) starts empty and packs again on first use."""

    def __init__(self) -> None:
        self._entries: "weakref.WeakKeyDictionary[nn.Module, _PackedWeights]" = weakref.WeakKeyDictionary()

    def get(self, conv: nn.Module) -> "_PackedWeights | None":
        return self._entries.get(conv)

    def put(self, conv: nn.Module, entry: "_PackedWeights") -> None:
        self._entries[conv] = entry

    def clear(self) -> None:
        self._entries.clear()

    def __len__(self) -> int:
        return len(self._entries)

    def __deepcopy__(self, memo: dict) -> "PrepackCache":
        return PrepackCache()

    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self.__init__()

_prepack_ok = True


def _dense(x: torch.Tensor) -> torch.Tensor:
    """``x`` when it is dense in the default or the channels_last layout, else a default-layout copy."""
    if x.is_contiguous() or x.is_contiguous(memory_format=torch.channels_last):
        return x
    return x.contiguous()


def simd_lanes() -> int:
    """float32 lanes of the vector unit oneDNN's x86 kernels use here: 16 with AVX-512, 8 with AVX2
    (also when ``ONEDNN_MAX_CPU_ISA`` / ``DNNL_MAX_CPU_ISA`` caps oneDNN below AVX-512), 0 on other
    CPUs (no lane-filling forms there: not measured)."""
    capability = torch.backends.cpu.get_cpu_capability()
    if capability not in ("AVX2", "AVX512"):
        return 0
    cap = (os.environ.get("ONEDNN_MAX_CPU_ISA") or os.environ.get("DNNL_MAX_CPU_ISA") or "ALL").upper()
    if capability == "AVX512" and (cap == "ALL" or cap.startswith(("AVX512", "AVX10"))):
        return 16
    return 8


def _narrow_form(conv: nn.Module, x: torch.Tensor) -> str:
    """How to run ``conv`` (the U-Net's k4 s2 p1 shape) on ``x`` with prepacked weights.

    oneDNN vectorises CPU convolutions over output channels, so a layer whose output channels fill
    at most half the SIMD lanes (8 channels with AVX-512's 16) leaves lanes idle (the small
    widths' 9 -> 8 first conv ran at ~50 GFLOP/s against ~100 for a full-width conv here).
    Such layers on maps of >= ``CHANNELS_LAST_MIN_PIXELS`` output pixels are widened:

    * ``"column_pairs"`` (conv): one conv computes two horizontally adjacent output pixels per
      position (kernel 4 x 6, stride 2 x 4, 2 C_out channels, zero taps where a pixel's window
      does not reach). Its channels_last output *is* the C_out-channel map, as a view. 1.5x the
      multiply-adds, full lanes: 9 -> 8 at 256^2 0.70 -> 0.54 ms, bit-identical.
    * ``"phases"`` (transposed conv): its sub-pixel decomposition, one 2 x 2 conv over the input
      padded by 1 that outputs the four output phases (4 C_out channels, exact multiply-adds plus
      one row and column), interleaved into the output (or the caller's ``out``, replacing the
      copy into the skip concatenation). 32 -> 8 at 64^2 -> 128^2: 0.67 -> 0.44 ms.

    Everything else is ``"direct"`` (``"transposed"`` for transposed convs). With AVX2 (8 lanes) a
    C_out of 8 fills the lanes and is left direct (column pairs were slower there: 0.78 -> 0.89 ms).
    """
    transposed = isinstance(conv, nn.ConvTranspose2d)
    direct = "transposed" if transposed else "direct"
    narrow = 2 * conv.out_channels <= simd_lanes()
    if not narrow or conv.kernel_size != (4, 4) or conv.stride != (2, 2) or conv.padding != (1, 1) \
            or conv.dilation != (1, 1):
        return direct
    h, w = x.shape[-2:]
    if transposed:
        return "phases" if conv.output_padding == (0, 0) and 4 * h * w >= CHANNELS_LAST_MIN_PIXELS else direct
    h_out, w_out = h // 2, w // 2
    return "column_pairs" if w_out % 2 == 0 and h_out * w_out >= CHANNELS_LAST_MIN_PIXELS else direct


_PHASE_TAPS = torch.tensor([[3, 1], [2, 0]])
"""For a k4 s2 p1 transposed conv, output index 2 m + a sums input m - 1 + a + d times kernel tap
``_PHASE_TAPS[a, d]`` = 3 - a - 2 d, d = 0, 1."""


def _phase_weights(weight: torch.Tensor) -> torch.Tensor:
    """(C_in, C, 4, 4) transposed-conv weights -> (4 C, C_in, 2, 2) conv weights whose output channel
    (2 a + b) C + c at padded-input position (i, j) is output pixel (2 (i - a) + a, 2 (j - b) + b)."""
    c_in, c = weight.shape[:2]
    taps = weight[:, :, _PHASE_TAPS][..., _PHASE_TAPS]  # (C_in, C, a, dy, b, dx)
    return taps.permute(2, 4, 1, 0, 3, 5).reshape(4 * c, c_in, 2, 2)


def _interleave_phases(phases: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """Write (N, 4 C, h + 1, w + 1) phase maps into ``out`` (N, C, 2 h, 2 w); returns ``out``."""
    c = out.shape[1]
    h, w = out.shape[-2] // 2, out.shape[-1] // 2
    for a in (0, 1):
        for b in (0, 1):
            k = 2 * a + b
            out[:, :, a::2, b::2].copy_(phases[:, k * c : (k + 1) * c, a : a + h, b : b + w])
    return out


def _column_pair_weights(weight: torch.Tensor, stride: int) -> torch.Tensor:
    """(C, C_in, kh, kw) conv weights -> (2 C, C_in, kh, kw + stride): channels C.. 2C are the same
    filter one output pixel (``stride`` input columns) to the right."""
    c, c_in, kh, kw = weight.shape
    pairs = weight.new_zeros(2 * c, c_in, kh, kw + stride)
    pairs[:c, :, :, :kw] = weight
    pairs[c:, :, :, stride:] = weight
    return pairs


def _merge_column_pairs(y: torch.Tensor) -> torch.Tensor:
    """(N, 2 C, H, W / 2) column-pair output -> the (N, C, H, W) map, a channels_last view."""
    y = y.contiguous(memory_format=torch.channels_last)
    n, c2, h, w2 = y.shape
    return y.permute(0, 2, 3, 1).reshape(n, h, 2 * w2, c2 // 2).permute(0, 3, 1, 2)


def _pack(conv: nn.Module, epilogue: Epilogue, x: torch.Tensor, items: tuple, states: tuple) -> _PackedWeights:
    """Fold ``epilogue`` into ``conv``'s weights and reorder them for oneDNN in the form
    :func:`_narrow_form` picks for ``x``."""
    transposed = isinstance(conv, nn.ConvTranspose2d)
    form = _narrow_form(conv, x)
    weight, bias = epilogue.folded(conv.weight.detach(), None if conv.bias is None else conv.bias.detach(),
                                   1 if transposed else 0)
    padding, stride, dilation = list(conv.padding), list(conv.stride), list(conv.dilation)
    output_padding = list(conv.output_padding) if transposed else [0, 0]
    if form == "phases":
        weight, stride = _phase_weights(weight), [1, 1]
        bias = None if bias is None else bias.repeat(4)
    elif form == "column_pairs":
        weight, stride = _column_pair_weights(weight, stride[1]), [stride[0], 2 * stride[1]]
        bias = None if bias is None else bias.repeat(2)
    if form == "transposed":
        packed = torch.ops.mkldnn._reorder_convolution_transpose_weight(
            weight.contiguous(), padding, output_padding, stride, dilation, 1, list(x.shape)
        )
    else:
        packed = torch._C._nn.mkldnn_reorder_conv2d_weight(
            weight.contiguous().to_mkldnn(), padding, stride, dilation, 1, list(x.shape)
        )
    attr, scalars = _onednn_attr(epilogue)
    return _PackedWeights(items, states, form, packed, None if bias is None else bias.contiguous(), padding, stride,
                          dilation, output_padding, attr, scalars)


def _packed_conv(
    conv: nn.Module, x: torch.Tensor, epilogue: Epilogue, cache: PrepackCache, out: torch.Tensor | None = None
) -> torch.Tensor | None:
    """``act(conv(x) * scale + shift)`` in one oneDNN call with prepacked weights (inference, CPU,
    float32), written into ``out`` when given (which is returned): the norm folded into the
    weights and the activation into the kernel, the weights reordered to oneDNN's blocked layout
    once and kept per module in ``cache`` until the weights, the norm or the input shape
    change (:func:`_pack_key`). torch otherwise reorders them on every call, a full extra pass over
    the 8-34 MB weights of the deep layers (1.5-2x their time here); this is what torch.compile's
    weight freezing does for CPU convolutions. Narrow layers run in a lane-filling form
    (:func:`_narrow_form`). None when oneDNN or these private torch ops are unavailable (logged
    once; callers use their other paths)."""
    global _prepack_ok
    if (
        not _prepack_ok
        or x.device.type != "cpu"
        or x.dtype != torch.float32
        or conv.weight.dtype != torch.float32
        or epilogue.act not in _ONEDNN_ATTR
        or conv.groups != 1
        or conv.padding_mode != "zeros"
        or not isinstance(conv.padding, tuple)
        or not torch.backends.mkldnn.is_available()
    ):
        return None
    items, states = _pack_key(conv, epilogue, x)
    entry = cache.get(conv)
    try:
        if entry is None or not entry.matches(items, states):
            entry = _pack(conv, epilogue, x, items, states)
            cache.put(conv, entry)
        return entry(x, out)
    except (AttributeError, RuntimeError, NotImplementedError) as exc:
        _prepack_ok = False  # the torch build cannot: true for every U-Net of the process
        cache.clear()
        logger.info("unet: oneDNN prepacked convolution unavailable (%s); using the unpacked paths", exc)
        return None


class Conv2d(nn.Conv2d):
    """``nn.Conv2d`` (same parameters, same result up to float rounding) tuned for CPU: large maps
    in channels_last, small maps as one matrix product of the weights with the unfolded input.

    Outside autograd, ``forward(x, epilogue=...)`` also applies a per-channel scale, shift and
    activation (the U-Net's norm and LeakyReLU) to the result, with weights prepacked into
    ``prepacked`` when given."""

    def forward(
        self, x: torch.Tensor, *, epilogue: Epilogue | None = None, prepacked: PrepackCache | None = None
    ) -> torch.Tensor:
        _check_fused(epilogue, None)
        if epilogue is not None and prepacked is not None:
            # large NCHW maps (the U-Net's input) in channels_last; others as they come
            large = x.shape[-2] * x.shape[-1] >= CHANNELS_LAST_MIN_PIXELS
            y = _packed_conv(self, channels_last(x) if large else _dense(x), epilogue, prepacked)
            if y is not None:
                return y
        if _gemm_ok(x, self):
            return _finish(self._gemm(x), epilogue, None)
        if epilogue is None:
            return super().forward(_cpu_layout(x))
        h_out = (x.shape[-2] + 2 * self.padding[0] - self.kernel_size[0]) // self.stride[0] + 1
        w_out = (x.shape[-1] + 2 * self.padding[1] - self.kernel_size[1]) // self.stride[1] + 1
        if self.weight.numel() > x.shape[0] * self.out_channels * h_out * w_out:
            return epilogue.apply_(self._conv_forward(_cpu_layout(x), self.weight, self.bias))
        # scale and shift folded into the (smaller) weights and bias: no passes over the output
        weight, bias = epilogue.folded(self.weight, self.bias, 0)
        return epilogue.activate_(self._conv_forward(_cpu_layout(x), weight, bias))

    def _gemm(self, x: torch.Tensor) -> torch.Tensor:
        b, _, h, w = x.shape
        (kh, kw), (sh, sw), (ph, pw) = self.kernel_size, self.stride, self.padding
        h_out, w_out = (h + 2 * ph - kh) // sh + 1, (w + 2 * pw - kw) // sw + 1
        cols = F.unfold(x, self.kernel_size, padding=self.padding, stride=self.stride)  # (B, C_in kh kw, L)
        weight = self.weight.reshape(self.out_channels, -1)  # (C_out, C_in kh kw)
        # W @ cols with cols transposed in memory (L rows of C_in kh kw values): MKL then streams the
        # weights as dot products (2-3x faster than W @ cols for L = 4 on this CPU)
        ys = [torch.mm(weight, cols[i].t().contiguous().t()) for i in range(b)]  # (C_out, L) each
        y = (ys[0].unsqueeze(0) if b == 1 else torch.stack(ys)).reshape(b, self.out_channels, h_out, w_out)
        return y if self.bias is None else y + self.bias.view(1, -1, 1, 1)


class ConvTranspose2d(nn.ConvTranspose2d):
    """``nn.ConvTranspose2d`` (same parameters, same result up to float rounding) tuned for CPU:
    large maps in channels_last, small maps as one matrix product followed by ``fold`` (col2im).

    Outside autograd, ``forward(x, epilogue=..., out=...)`` also applies a per-channel scale, shift
    and activation (the U-Net's norm and ReLU) and writes the result into ``out`` (e.g. the first
    half of the skip concatenation's buffer), which it returns; weights are prepacked into
    ``prepacked`` when given."""

    def forward(
        self,
        x: torch.Tensor,
        output_size: list[int] | None = None,
        *,
        epilogue: Epilogue | None = None,
        out: torch.Tensor | None = None,
        prepacked: PrepackCache | None = None,
    ) -> torch.Tensor:
        _check_fused(epilogue, out)
        if epilogue is not None and prepacked is not None and output_size is None:
            y = _packed_conv(self, _dense(x), epilogue, prepacked, out)
            if y is not None:
                return y
        if output_size is not None or self.output_padding != (0, 0):
            x = _cpu_layout(x, CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS)
            return _finish(super().forward(x, output_size), epilogue, out)
        if _gemm_ok(x, self):
            return _finish(self._gemm(x), epilogue, out)
        x = _cpu_layout(x, CONV_TRANSPOSE_CHANNELS_LAST_MIN_PIXELS)
        if epilogue is None or self.weight.numel() > x.shape[0] * self.out_channels * 4 * x.shape[-2] * x.shape[-1]:
            return _finish(super().forward(x), epilogue, out)
        # scale and shift folded into the (smaller) weights, the activation into oneDNN's kernel
        weight, bias = epilogue.folded(self.weight, self.bias, 1)
        y = _onednn_act(True, x, weight, bias, epilogue, self.padding, self.stride, self.dilation, self.groups,
                        self.output_padding)
        if y is None:
            y = epilogue.activate_(self._conv_transpose(x, weight, bias))
        return _finish(y, None, out)

    def _conv_transpose(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        return F.conv_transpose2d(x, weight, bias, self.stride, self.padding, self.output_padding, self.groups,
                                  self.dilation)

    def _gemm(self, x: torch.Tensor) -> torch.Tensor:
        b, c_in, h, w = x.shape
        (kh, kw), (sh, sw), (ph, pw) = self.kernel_size, self.stride, self.padding
        h_out, w_out = (h - 1) * sh - 2 * ph + kh, (w - 1) * sw - 2 * pw + kw
        xm = x.reshape(b, c_in, h * w)
        weight = self.weight.reshape(c_in, -1)  # (C_in, C_out kh kw)
        # x^T @ W (MKL streams W's rows; W^T @ x is up to 10x slower for 4-pixel maps here)
        cols = [torch.mm(xm[i].t(), weight) for i in range(b)]  # (H W, C_out kh kw) each
        cols_t = (cols[0].unsqueeze(0) if b == 1 else torch.stack(cols)).transpose(1, 2)
        y = F.fold(cols_t, (h_out, w_out), self.kernel_size, padding=self.padding, stride=self.stride)
        return y if self.bias is None else y + self.bias.view(1, -1, 1, 1)
