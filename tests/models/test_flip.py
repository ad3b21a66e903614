"""FLIP (deliffas.models.flip): the flip-evaluator package's LDR-FLIP, called the way the evaluator calls it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.models.flip import flip_error, flip_map, flip_status

flip_evaluator = pytest.importorskip("flip_evaluator", reason="flip-evaluator is not installed (pip install flip-evaluator)")


def test_flip_matches_the_package_and_grows_with_the_error():
    assert flip_status() is None
    gen = torch.Generator().manual_seed(0)
    gt = torch.rand(3, 40, 32, generator=gen)
    assert flip_error(gt, gt) == 0.0
    errors = [flip_error((gt + s * torch.randn(3, 40, 32, generator=gen)).clamp(0, 1), gt) for s in (0.02, 0.1, 0.3)]
    assert errors == sorted(errors) and 0 < errors[0] and errors[-1] < 1
    pred = (gt + 0.1).clamp(0, 1)
    ref = np.ascontiguousarray(gt.permute(1, 2, 0).numpy(), dtype=np.float32)
    test = np.ascontiguousarray(pred.permute(1, 2, 0).numpy(), dtype=np.float32)
    _, mean, _ = flip_evaluator.evaluate(ref, test, "LDR", applyMagma=False)
    assert flip_error(pred, gt) == pytest.approx(mean, rel=1e-5)
    assert flip_map(pred, gt).shape == (40, 32)
    with pytest.raises(ValueError, match="differ"):
        flip_error(pred[:, :10], gt)
