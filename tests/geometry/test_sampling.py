"""Tests of deliffas.geometry.sampling.sample_uv (texel-centre convention, batching, gradients)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.geometry.sampling import sample_uv


def uv_centre_map(size: int, dtype=torch.float32) -> torch.Tensor:
    """(1, 2, S, S) map whose texel (i, j) holds its own uv centre ((j+.5)/S, 1-(i+.5)/S)."""
    idx = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    u = idx.view(1, size).expand(size, size)
    v = (1.0 - idx).view(size, 1).expand(size, size)
    return torch.stack([u, v])[None].to(dtype)


def reference_bilinear(maps: np.ndarray, batch_index: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Loop oracle: texel centres at ((j+.5)/S, 1-(i+.5)/S), clamped to the border centres."""
    _, channels, height, width = maps.shape
    out = np.zeros((len(uv), channels))
    for n, ((u, v), b) in enumerate(zip(uv, batch_index)):
        x = min(max(u * width - 0.5, 0.0), width - 1.0)
        y = min(max((1.0 - v) * height - 0.5, 0.0), height - 1.0)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        x1, y1 = min(x0 + 1, width - 1), min(y0 + 1, height - 1)
        fx, fy = x - x0, y - y0
        out[n] = (
            maps[b, :, y0, x0] * (1 - fx) * (1 - fy)
            + maps[b, :, y0, x1] * fx * (1 - fy)
            + maps[b, :, y1, x0] * (1 - fx) * fy
            + maps[b, :, y1, x1] * fx * fy
        )
    return out


def test_returns_query_uv_on_uv_centre_map(device):
    size = 16
    maps = uv_centre_map(size).to(device)
    gen = torch.Generator().manual_seed(0)
    lo, hi = 0.5 / size, 1.0 - 0.5 / size
    uv = (lo + (hi - lo) * torch.rand(500, 2, generator=gen)).to(device)
    out = sample_uv(maps, torch.zeros(500, dtype=torch.long, device=device), uv)
    assert out.shape == (500, 2)
    torch.testing.assert_close(out, uv, rtol=0, atol=1e-5)


def test_texel_centres_are_exact():
    size = 8
    maps = torch.arange(size * size, dtype=torch.float32).view(1, 1, size, size)
    i, j = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    uv = torch.stack([(j.flatten() + 0.5) / size, 1 - (i.flatten() + 0.5) / size], dim=-1)
    out = sample_uv(maps, torch.zeros(size * size, dtype=torch.long), uv)
    torch.testing.assert_close(out[:, 0], maps.flatten(), rtol=0, atol=1e-4)


def test_border_padding():
    size = 4
    maps = uv_centre_map(size)
    uv = torch.tensor([[-0.3, 0.5], [1.2, 1.7], [0.0, 0.0]])
    out = sample_uv(maps, torch.zeros(3, dtype=torch.long), uv)
    lo, hi = 0.5 / size, 1 - 0.5 / size
    expected = torch.tensor([[lo, 0.5], [hi, hi], [lo, lo]])
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("sorted_index", [True, False])
def test_batched_matches_loop_oracle(sorted_index):
    gen = torch.Generator().manual_seed(1)
    maps = torch.randn(3, 5, 6, 6, generator=gen, dtype=torch.float64)
    batch_index = torch.randint(0, 3, (200,), generator=gen)
    batch_index[:3] = torch.tensor([2, 0, 1])
    if sorted_index:
        batch_index = batch_index.sort().values
    uv = torch.rand(200, 2, generator=gen, dtype=torch.float64) * 1.2 - 0.1
    out = sample_uv(maps, batch_index, uv)
    ref = reference_bilinear(maps.numpy(), batch_index.numpy(), uv.numpy())
    np.testing.assert_allclose(out.numpy(), ref, rtol=0, atol=1e-10)


def test_batch_without_some_items():
    maps = torch.stack([torch.full((2, 4, 4), float(b)) for b in range(4)])
    batch_index = torch.tensor([3, 3, 1, 3])
    out = sample_uv(maps, batch_index, torch.rand(4, 2))
    torch.testing.assert_close(out[:, 0], batch_index.float())


def test_gradients_reach_maps_and_uv():
    maps = torch.randn(2, 3, 8, 8, requires_grad=True)
    uv = torch.rand(50, 2, requires_grad=True)
    batch_index = torch.randint(0, 2, (50,))
    sample_uv(maps, batch_index, uv).square().sum().backward()
    assert maps.grad is not None and maps.grad.abs().sum() > 0
    assert uv.grad is not None and torch.isfinite(uv.grad).all() and uv.grad.abs().sum() > 0


def test_empty_and_errors(unchecked):
    maps = torch.randn(2, 3, 8, 8)
    assert sample_uv(maps, torch.zeros(0, dtype=torch.long), torch.zeros(0, 2)).shape == (0, 3)
    with unchecked(), pytest.raises(ValueError, match="batch_index"):
        sample_uv(maps, torch.tensor([0, 2]), torch.rand(2, 2))
    with unchecked(), pytest.raises(ValueError, match="integer"):
        sample_uv(maps, torch.tensor([0.0, 1.0]), torch.rand(2, 2))
    with unchecked(), pytest.raises(ValueError, match="uv"):
        sample_uv(maps, torch.tensor([0, 1]), torch.rand(2, 3))
    with unchecked(), pytest.raises(ValueError, match="batch_index"):
        sample_uv(maps[:1], torch.tensor([0, 1]), torch.rand(2, 2))


@pytest.mark.parametrize("shape", [(1, 5, 8, 8), (3, 4, 6, 10)])
def test_the_gather_path_agrees_with_grid_sample(shape):
    """Training (map needs a gradient, uv not, channels-last) gathers and scatter-adds instead of
    calling grid_sample: same values, same map gradient, uv outside [0, 1] included (border)."""
    import torch.nn.functional as F

    from deliffas.geometry.sampling import uv_to_grid

    gen = torch.Generator().manual_seed(0)
    B, C, H, W = shape
    maps = torch.randn(shape, generator=gen).contiguous(memory_format=torch.channels_last).requires_grad_()
    n = 400
    uv = torch.rand(n, 2, generator=gen) * 1.2 - 0.1
    uv[:4] = torch.tensor([[0.0, 0.0], [1.0, 1.0], [0.5 / W, 1 - 0.5 / H], [1 - 0.5 / W, 0.5 / H]])
    batch = torch.randint(0, B, (n,), generator=gen)
    got = sample_uv(maps, batch, uv)
    grad_out = torch.randn(n, C, generator=gen)
    (got_grad,) = torch.autograd.grad(got, maps, grad_out)
    ref_maps = maps.detach().contiguous().requires_grad_()  # contiguous NCHW: the grid_sample path
    ref = torch.stack([F.grid_sample(ref_maps[b : b + 1], uv_to_grid(uv[i : i + 1]).view(1, 1, 1, 2),
                                     mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0, 0]
                       for i, b in enumerate(batch.tolist())])
    (ref_grad,) = torch.autograd.grad(ref, ref_maps, grad_out)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-5)
    torch.testing.assert_close(got_grad, ref_grad, rtol=0, atol=1e-5)


def test_uv_that_need_a_gradient_still_get_one():
    maps = torch.randn(1, 3, 8, 8).contiguous(memory_format=torch.channels_last).requires_grad_()
    uv = torch.rand(20, 2).requires_grad_()
    (g,) = torch.autograd.grad(sample_uv(maps, torch.zeros(20, dtype=torch.long), uv).sum(), uv)
    assert g.abs().sum() > 0


def _no_kernel(monkeypatch):
    """The gather's C kernel unavailable, as without a compiler."""
    import deliffas.geometry.sampling as sampling
    from deliffas.native import LazyLibrary, NativeLibrary

    lib = LazyLibrary("gather_bilinear", sampling._KERNEL.source, fallback="torch")
    monkeypatch.setattr(lib, "_built", NativeLibrary(None, "test: no compiler"))
    monkeypatch.setattr(sampling, "_KERNEL", lib)


def _gather_case(shape, seed=0):
    """Channels-last maps that need a gradient, uv over [-0.1, 1.1]^2 with the corners, the outermost
    texel centres and the borders, a batch index and an output gradient."""
    gen = torch.Generator().manual_seed(seed)
    B, C, H, W = shape
    maps = torch.randn(shape, generator=gen).contiguous(memory_format=torch.channels_last)
    n = 500
    uv = torch.rand(n, 2, generator=gen) * 1.2 - 0.1
    edges = [[0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0], [0.5 / W, 1 - 0.5 / H], [1 - 0.5 / W, 0.5 / H],
             [-3.0, 0.5], [0.5, 7.0], [1.0, 0.3], [0.3, 1.0]]
    uv[: len(edges)] = torch.tensor(edges)
    batch = torch.randint(0, B, (n,), generator=gen)
    return maps, batch, uv, torch.randn(n, C, generator=gen)


def _sample_and_grad(maps, batch, uv, grad_out):
    maps = maps.detach().clone(memory_format=torch.channels_last).requires_grad_()
    out = sample_uv(maps, batch, uv)
    (grad,) = torch.autograd.grad(out, maps, grad_out)
    return out, grad


@pytest.mark.parametrize("shape", [(1, 24, 16, 16), (2, 3, 8, 12), (3, 5, 6, 10), (1, 32, 4, 4)])
def test_the_compiled_gather_agrees_with_the_torch_gather(shape, monkeypatch):
    """The C kernel (CPU float32) and torch's index_select / index_add_ give the same values and map
    gradients, up to float summation order; the compiled backward is deterministic."""
    import deliffas.geometry.sampling as sampling

    built = sampling._KERNEL.load()
    if built.lib is None and built.reason.startswith(("disabled", "no C compiler")):
        pytest.skip(built.reason)
    assert built.lib is not None, built.reason  # this project's machines have a compiler
    case = _gather_case(shape)
    got, got_grad = _sample_and_grad(*case)
    again, again_grad = _sample_and_grad(*case)
    assert torch.equal(got, again) and torch.equal(got_grad, again_grad)
    _no_kernel(monkeypatch)
    ref, ref_grad = _sample_and_grad(*case)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-5)
    torch.testing.assert_close(got_grad, ref_grad, rtol=0, atol=1e-5)


def test_the_gather_without_the_kernel(monkeypatch):
    """DELIFFAS_NATIVE=0: the torch gather, logged at INFO, the values of grid_sample."""
    import deliffas.geometry.sampling as sampling
    from deliffas.native import NATIVE_ENV, LazyLibrary

    monkeypatch.setenv(NATIVE_ENV, "0")
    monkeypatch.setattr(sampling, "_KERNEL", LazyLibrary("gather_bilinear", sampling._KERNEL.source, fallback="torch"))
    maps, batch, uv, grad_out = _gather_case((2, 4, 8, 8))
    out, grad = _sample_and_grad(maps, batch, uv, grad_out)
    assert "disabled" in sampling._KERNEL.load().reason
    ref = sample_uv(maps.contiguous(), batch, uv)  # default layout: grid_sample
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-5)
    assert grad.abs().sum() > 0


@pytest.mark.parametrize("compiled", [True, False])
def test_gather_indices_out_of_range_raise(compiled, monkeypatch):
    """Corners outside the map (NaN uv) raise torch's index error on either path, never read out of bounds."""
    from deliffas.geometry.sampling import _GatherBilinear

    if not compiled:
        _no_kernel(monkeypatch)
    maps = torch.randn(1, 3, 4, 4).contiguous(memory_format=torch.channels_last).requires_grad_()
    index = torch.zeros(4, 5, dtype=torch.long)
    index[2, 3] = 16
    with pytest.raises((IndexError, RuntimeError), match="index|out of"):
        _GatherBilinear.apply(maps, index, torch.full((4, 5), 0.25))
    with pytest.raises((IndexError, RuntimeError), match="index|out of"):
        sample_uv(maps, torch.zeros(2, dtype=torch.long), torch.tensor([[0.5, 0.5], [float("nan"), 0.5]]))
