"""The U-Nets' training sigmoid with the saturation penalty in one node (models.feature_sigmoid): the same
features and, to the bit, the same logit gradient as torch's sigmoid and ``saturation_penalty`` as two nodes,
with the C kernel and without it."""

from __future__ import annotations

import pytest
import torch

from deliffas.models import feature_sigmoid
from deliffas.models.feature_sigmoid import sigmoid_with_penalty
from deliffas.models.losses import SaturationTerm, saturation_penalty
from deliffas.native import LazyLibrary, NativeLibrary


def _no_kernel(monkeypatch):
    lib = LazyLibrary("feature_sigmoid", feature_sigmoid._KERNEL.source, fallback="torch")
    monkeypatch.setattr(lib, "_built", NativeLibrary(None, "test: no compiler"))
    monkeypatch.setattr(feature_sigmoid, "_KERNEL", lib)


def _case(channels_last: bool, seed: int = 0):
    """Logits over [-9, 9] with values at and next to the margin 4, and a features gradient, in one layout."""
    gen = torch.Generator().manual_seed(seed)
    s = torch.randn(1, 16, 24, 20, generator=gen) * 4
    flat = s.view(-1)
    flat[:8] = torch.tensor([4.0, -4.0, 4.0000005, -4.0000005, 3.9999998, 9.0, -9.0, 0.0])
    g = torch.randn(s.shape, generator=gen)
    layout = torch.channels_last if channels_last else torch.contiguous_format
    return s.contiguous(memory_format=layout), g.contiguous(memory_format=layout)


def _separate(s, g, weight):
    s = s.clone().requires_grad_()
    y, p = torch.sigmoid(s), saturation_penalty([s], 4.0)
    torch.autograd.backward([y, weight * p], [g, None])
    return y.detach(), p.detach(), s.grad


def _fused(s, g, weight):
    s = s.clone().requires_grad_()
    y, p = sigmoid_with_penalty(s, 4.0)
    torch.autograd.backward([y, weight * torch.stack([p]).sum()], [g, None])
    return y.detach(), p.detach(), s.grad


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("channels_last", [True, False])
def test_one_node_gives_the_two_nodes_gradient_to_the_bit(native, channels_last, monkeypatch):
    if native:
        built = feature_sigmoid._KERNEL.load()
        if built.lib is None and built.reason.startswith(("disabled", "no C compiler")):
            pytest.skip(built.reason)
        assert built.lib is not None, built.reason  # this project's machines have a compiler
    else:
        _no_kernel(monkeypatch)
    s, g = _case(channels_last)
    y0, p0, grad0 = _separate(s, g, 0.01)
    y1, p1, grad1 = _fused(s, g, 0.01)
    assert torch.equal(y0, y1) and torch.equal(grad0, grad1)
    assert grad1.is_contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    assert float(p1) == pytest.approx(float(p0), rel=1e-6) and float(p1) > 0


def test_either_output_alone_has_its_own_gradient():
    s, g = _case(True)
    a = s.clone().requires_grad_()
    (grad_features,) = torch.autograd.grad(sigmoid_with_penalty(a, 4.0)[0], a, g)
    assert torch.equal(grad_features, torch.autograd.grad(torch.sigmoid(a), a, g)[0])
    (grad_penalty,) = torch.autograd.grad(3.0 * sigmoid_with_penalty(a, 4.0)[1], a)
    assert torch.equal(grad_penalty, torch.autograd.grad(3.0 * saturation_penalty([a], 4.0), a)[0])
    with pytest.raises(ValueError, match="margin"):
        sigmoid_with_penalty(a, 0.0)


def test_the_model_computes_the_penalty_with_its_sigmoid_when_asked():
    """``track_saturation``: the U-Nets' training forward computes the penalty the term reads, equal to the one
    from their logits; a margin the forward did not use falls back to the logits."""
    from deliffas.engine.train import TrainConfig, resolve_model_config
    from deliffas.models import DeliffasModel

    torch.manual_seed(0)
    model = DeliffasModel(resolve_model_config(TrainConfig(shards="-", out="-", preset="tiny"), 32, 2))
    normals = [torch.rand(1, 9, 32, 32) * 2 - 1 for _ in range(2)]
    term = SaturationTerm(1.0, 1e-3)  # non-zero on untrained U-Nets
    model.encode(*normals)
    assert model.feature_penalties(term.margin) is None  # not tracked: the logits' penalty
    from_logits = term.penalty(model)
    model.track_saturation(term.margin)
    model.encode(*normals)
    tracked = model.feature_penalties(term.margin)
    assert tracked is not None and len(tracked) == len(model.feature_logits()) == 2
    assert float(term.penalty(model).detach()) == pytest.approx(float(from_logits.detach()), rel=1e-6)
    assert float(from_logits.detach()) > 0
    assert model.feature_penalties(2.0) is None
    with torch.no_grad():
        model.encode(*normals)
    assert model.feature_penalties(term.margin) == [] and float(term.penalty(model)) == 0.0
