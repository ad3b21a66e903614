"""Tests of deliffas.models.encoding."""

from __future__ import annotations

import math

import pytest
import torch

from deliffas.models.encoding import PositionalEncoding, encoded_dim, positional_encoding


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
