"""Prepacked oneDNN convolutions for the U-Net's inference on CPU: folded weights kept in oneDNN's
blocked layout per module (:class:`PrepackCache`, held by a U-Net after ``optimize_for_inference``)
until their sources change, and lane-filling forms (column pairs, output phases) for layers too
narrow to fill the SIMD lanes.
"""

from __future__ import annotations

import logging
import weakref
from dataclasses import dataclass

import torch
from torch import nn

from deliffas import environment
from deliffas.models.unet_cpu import CHANNELS_LAST_MIN_PIXELS, Epilogue, finish_output, new_map

logger = logging.getLogger(__name__)


_onednn_pointwise_ok = True
"""False once this torch build has refused oneDNN's fused pointwise convolution (then torch's own path runs)."""

_ONEDNN_ATTR = {"relu": "relu", "leaky_relu": "leaky_relu", "sigmoid": "sigmoid", None: "none"}


def _onednn_attr(epilogue: Epilogue) -> tuple[str, list]:
    """oneDNN's post-op name and scalars for the epilogue's activation (one of ``_ONEDNN_ATTR``)."""
    return _ONEDNN_ATTR[epilogue.act], [epilogue.slope] if epilogue.act == "leaky_relu" else []


def onednn_act(
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
        return finish_output(y, None, out)


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


def simd_lanes() -> int:
    """float32 lanes of the vector unit oneDNN's x86 kernels use here: 16 with AVX-512, 8 with AVX2
    (also when ``ONEDNN_MAX_CPU_ISA`` / ``DNNL_MAX_CPU_ISA`` caps oneDNN below AVX-512), 0 on other
    CPUs (no lane-filling forms there: not measured)."""
    capability = torch.backends.cpu.get_cpu_capability()
    if capability not in ("AVX2", "AVX512"):
        return 0
    cap = environment.onednn_isa_cap()
    if capability == "AVX512" and (cap == "ALL" or cap.startswith(("AVX512", "AVX10"))):
        return 16
    return 8


def _narrow_form(conv: nn.Module, x: torch.Tensor) -> str:
    """How to run ``conv`` (the U-Net's k4 s2 p1 shape) on ``x`` with prepacked weights.

    oneDNN vectorises CPU convolutions over output channels, so a layer whose output channels fill
    at most half the SIMD lanes (8 channels with AVX-512's 16) leaves lanes idle (the small
    widths' 9 -> 8 first conv runs at about half the rate of a full-width conv).
    Such layers on maps of >= ``CHANNELS_LAST_MIN_PIXELS`` output pixels are widened:

    * ``"column_pairs"`` (conv): one conv computes two horizontally adjacent output pixels per
      position (kernel 4 x 6, stride 2 x 4, 2 C_out channels, zero taps where a pixel's window
      does not reach). Its channels_last output *is* the C_out-channel map, as a view. 1.5x the
      multiply-adds, full lanes, bit-identical.
    * ``"phases"`` (transposed conv): its sub-pixel decomposition, one 2 x 2 conv over the input
      padded by 1 that outputs the four output phases (4 C_out channels, exact multiply-adds plus
      one row and column), interleaved into the output (or the caller's ``out``, replacing the
      copy into the skip concatenation).

    Everything else is ``"direct"`` (``"transposed"`` for transposed convs). With AVX2 (8 lanes) a
    C_out of 8 fills the lanes and is left direct (column pairs are slower there).
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


def packed_conv(
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

