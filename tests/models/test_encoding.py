"""Tests of deliffas.models.encoding."""

from __future__ import annotations

import math

import pytest
import torch

from deliffas.models.encoding import PositionalEncoding, encode_parts, encoded_dim, positional_encoding


def test_shape_and_out_dim(device):
    x = torch.rand(5, 7, 2, device=device)
    y = positional_encoding(x, num_freqs=3)
    assert y.shape == (5, 7, 2 + 2 * 2 * 3)
    assert PositionalEncoding(2, 10).out_dim == 42 == encoded_dim(2, 10)
    assert PositionalEncoding(3, 4, include_input=False).out_dim == 24


def test_values_and_order():
    x = torch.tensor([[0.25, 0.1]], dtype=torch.float64)
    y = positional_encoding(x, num_freqs=2)[0]
    u, v = 0.25, 0.1
    expected = [
        u, v,
        math.sin(math.pi * u), math.sin(math.pi * v), math.cos(math.pi * u), math.cos(math.pi * v),
        math.sin(2 * math.pi * u), math.sin(2 * math.pi * v), math.cos(2 * math.pi * u), math.cos(2 * math.pi * v),
    ]  # fmt: skip
    torch.testing.assert_close(y, torch.tensor(expected, dtype=torch.float64), rtol=0, atol=1e-12)


def test_without_input_and_zero_freqs():
    x = torch.rand(4, 3)
    assert torch.equal(positional_encoding(x, 0), x)
    y = positional_encoding(x, 1, include_input=False)
    torch.testing.assert_close(y[:, :3], torch.sin(math.pi * x))


def test_gradient_flows():
    x = torch.rand(6, 2, requires_grad=True)
    positional_encoding(x, 4).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_module_checks_dim():
    pe = PositionalEncoding(2, 3)
    assert pe(torch.rand(8, 2)).shape == (8, pe.out_dim)
    with pytest.raises(ValueError, match="expected shape"):
        pe(torch.rand(8, 3))
    with pytest.raises(ValueError, match="num_freqs"):
        positional_encoding(torch.rand(2, 2), -1)


def _kernel():
    """The encoding kernel's library, skipping where this machine cannot build it."""
    from deliffas.models import encoding

    built = encoding._KERNEL.load()
    if built.lib is None and built.reason.startswith(("disabled", "no C compiler")):
        pytest.skip(built.reason)
    assert built.lib is not None, built.reason  # this project's machines have a compiler
    return encoding


def _no_kernel(monkeypatch):
    """The encoding kernel unavailable, as without a compiler."""
    from deliffas.models import encoding
    from deliffas.native import LazyLibrary, NativeLibrary

    lib = LazyLibrary("encoding", encoding._KERNEL.source, fallback="torch")
    monkeypatch.setattr(lib, "_built", NativeLibrary(None, "test: no compiler"))
    monkeypatch.setattr(encoding, "_KERNEL", lib)


def _coordinates(n: int, dim: int, scale: float, seed: int) -> torch.Tensor:
    """(n, dim) float32 over [-scale, scale] with 0, +-1, +-0.5, +-scale and tiny values in the first rows."""
    gen = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, dim, generator=gen) * 2 - 1) * scale
    special = torch.tensor([0.0, 1.0, -1.0, 0.5, -0.5, scale, -scale, 1e-7, -3e-30, 0.25])
    x[: len(special)] = special[:, None]
    return x


_SPECS = [(2, 10, True), (3, 4, True), (2, 1, False), (1, 0, True), (3, 16, False), (4, 6, True)]


@pytest.mark.parametrize("scale", [1.0, 10.0])
@pytest.mark.parametrize("spec", _SPECS)
def test_the_kernel_agrees_with_torch(spec, scale):
    """One part: the kernel's sin / cos of torch's float32 angles agree with torch's to ~1e-7."""
    encoding = _kernel()
    pe = PositionalEncoding(*spec)
    x = _coordinates(300, pe.in_dim, scale, seed=spec[1])
    got = encoding._encode_native([(x, pe)])
    assert got is not None and got.shape == (300, pe.out_dim) and got.dtype == torch.float32
    torch.testing.assert_close(got, positional_encoding(x, pe.num_freqs, pe.include_input), rtol=0, atol=1e-5)
    assert (got - positional_encoding(x, pe.num_freqs, pe.include_input)).abs().max() < 2e-6


def test_parts_are_concatenated_in_order():
    """The training's three parts (uv outer, uv inner, reflected direction) in one array, (N, 111), the torch
    concatenation's values; leading dimensions are kept and a non-contiguous input is read correctly."""
    encoding = _kernel()
    pe_uv, pe_dir = PositionalEncoding(2, 10), PositionalEncoding(3, 4)
    uv_outer, uv_inner = _coordinates(1000, 2, 1.1, 1), _coordinates(1000, 2, 1.0, 2)
    viewdir = torch.nn.functional.normalize(_coordinates(1000, 3, 1.0, 3) + 0.01, dim=-1)
    parts = [(uv_outer, pe_uv), (uv_inner, pe_uv), (viewdir, pe_dir)]
    got = encoding._encode_native(parts)
    ref = torch.cat([pe_uv(uv_outer), pe_uv(uv_inner), pe_dir(viewdir)], dim=-1)
    assert got is not None and got.shape == (1000, 111)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-5)
    batched = encode_parts([(uv_inner.view(10, 100, 2), pe_uv), (viewdir.view(10, 100, 3), pe_dir)])
    assert batched.shape == (10, 100, 42 + 27)
    torch.testing.assert_close(batched.view(1000, -1), ref[:, 42:], rtol=0, atol=1e-5)
    strided = torch.randn(2, 500)
    torch.testing.assert_close(encode_parts([(strided.T, pe_uv)]), pe_uv(strided.T), rtol=0, atol=1e-5)
    assert encode_parts([(uv_inner[:0], pe_uv)]).shape == (0, 42)


def test_out_of_range_and_nan_match_torch():
    """Coordinates beyond the kernel's range are encoded by torch; NaN encodes to NaN as in torch."""
    encoding = _kernel()
    pe = PositionalEncoding(2, 10)
    x = torch.tensor([[0.5, 3e5], [0.25, 0.75]])
    assert encoding._encode_native([(x, pe)]) is None
    torch.testing.assert_close(encode_parts([(x, pe)]), pe(x), rtol=0, atol=0)
    x = torch.tensor([[float("nan"), 0.5], [float("inf"), 0.25]])
    torch.testing.assert_close(encode_parts([(x, pe)]), pe(x), rtol=0, atol=1e-5, equal_nan=True)


def test_encode_parts_without_the_kernel(monkeypatch):
    """No compiler: torch's encodings, exactly."""
    _no_kernel(monkeypatch)
    pe_uv, pe_dir = PositionalEncoding(2, 10), PositionalEncoding(3, 4)
    uv, d = torch.rand(50, 2), torch.rand(50, 3)
    assert torch.equal(encode_parts([(uv, pe_uv), (d, pe_dir)]), torch.cat([pe_uv(uv), pe_dir(d)], dim=-1))


def test_encode_parts_with_native_disabled(monkeypatch):
    """DELIFFAS_NATIVE=0: the torch path, the library reports why."""
    from deliffas.models import encoding
    from deliffas.native import NATIVE_ENV, LazyLibrary

    monkeypatch.setenv(NATIVE_ENV, "0")
    monkeypatch.setattr(encoding, "_KERNEL", LazyLibrary("encoding", encoding._KERNEL.source, fallback="torch"))
    pe = PositionalEncoding(2, 3)
    uv = torch.rand(20, 2)
    assert torch.equal(encode_parts([(uv, pe)]), pe(uv))
    assert "disabled" in encoding._KERNEL.load().reason


def test_encode_parts_gradients_take_the_torch_path():
    """An input that requires grad is encoded by torch and gets its gradient; the other parts' values agree."""
    pe = PositionalEncoding(2, 4)
    uv = torch.rand(30, 2, requires_grad=True)
    other = torch.rand(30, 2)
    out = encode_parts([(other, pe), (uv, pe)])
    assert out.requires_grad
    (grad,) = torch.autograd.grad(out.sum(), uv)
    (ref,) = torch.autograd.grad(pe(uv).sum(), uv)
    torch.testing.assert_close(grad, ref)
    with torch.no_grad():
        torch.testing.assert_close(encode_parts([(other, pe), (uv, pe)]), out.detach(), rtol=0, atol=1e-5)


def test_encode_parts_other_dtypes_and_checks():
    """float64 and bfloat16 take the torch path (their own dtype); shapes are checked."""
    pe = PositionalEncoding(2, 3)
    for dtype in (torch.float64, torch.bfloat16):
        x = torch.rand(8, 2).to(dtype)
        out = encode_parts([(x, pe)])
        assert out.dtype == dtype and torch.equal(out, pe(x))
    with pytest.raises(ValueError, match="expected shape"):
        encode_parts([(torch.rand(8, 3), pe)])
    with pytest.raises(ValueError, match="at least one"):
        encode_parts([])
