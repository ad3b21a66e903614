"""FID (deliffas.models.fid): the statistics and Fréchet distance against scipy, the network's shapes and
weight names on random weights, the evaluator's FID from a weight file. Nothing is downloaded."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deliffas.models.fid import (FIDInceptionV3, activation_statistics, fid_from_features, frechet_distance,
                                 inception_candidates, load_fid_inception)


def scipy_frechet(mu1, sigma1, mu2, sigma2, eps=1e-6) -> float:
    """pytorch-fid's ``calculate_frechet_distance`` (scipy.linalg.sqrtm), written out for the test."""
    from scipy import linalg

    diff = mu1 - mu2
    covmean = linalg.sqrtm(sigma1.dot(sigma2))
    if not np.isfinite(covmean).all():
        offset = np.eye(sigma1.shape[0]) * eps
        covmean = linalg.sqrtm((sigma1 + offset).dot(sigma2 + offset))
    covmean = covmean.real
    return float(diff.dot(diff) + np.trace(sigma1) + np.trace(sigma2) - 2 * np.trace(covmean))


def test_statistics_and_frechet_match_scipy():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 16))
    b = rng.normal(loc=0.3, size=(150, 16)) @ rng.normal(size=(16, 16)) * 0.5
    mu, sigma = activation_statistics(a)
    np.testing.assert_allclose(mu, a.mean(axis=0))
    np.testing.assert_allclose(sigma, np.cov(a, rowvar=False))
    expected = scipy_frechet(*activation_statistics(a), *activation_statistics(b))
    assert fid_from_features(a, b) == pytest.approx(expected, rel=1e-8, abs=1e-8)
    assert fid_from_features(a, a) == pytest.approx(0.0, abs=1e-8)
    assert frechet_distance(np.zeros(2), np.eye(2), np.ones(2), 4 * np.eye(2)) == pytest.approx(2 + 2 + 8 - 2 * 4)
    with pytest.raises(ValueError, match="N >= 2"):
        activation_statistics(a[:1])


def test_network_shapes_and_pytorch_fid_weight_names():
    net = FIDInceptionV3()
    keys = set(net.state_dict())
    for key in ("Conv2d_1a_3x3.conv.weight", "Conv2d_4a_3x3.bn.running_var", "Mixed_5b.branch_pool.conv.weight",
                "Mixed_6e.branch7x7dbl_5.bn.bias", "Mixed_7a.branch7x7x3_4.conv.weight",
                "Mixed_7c.branch3x3dbl_3b.bn.running_mean"):
        assert key in keys
    # torchvision's inception_v3 (27,161,264 parameters) less its aux classifier (3,326,696) and fc (2,049,000)
    assert sum(p.numel() for p in net.parameters()) == 21_785_568
    with torch.no_grad():
        out = net(torch.rand(2, 3, 40, 56))
    assert out.shape == (2, 2048) and torch.isfinite(out).all() and (out >= 0).all()


def test_weight_file_round_trip_and_layout_errors(tmp_path):
    torch.manual_seed(0)
    net = FIDInceptionV3()
    state = {k: v for k, v in net.state_dict().items() if not k.endswith("num_batches_tracked")}
    state["fc.weight"] = torch.zeros(1008, 2048)  # pytorch-fid's file carries the classifier: ignored
    path = tmp_path / "pt_inception-2015-12-05-6726825d.pth"
    torch.save(state, path)
    loaded = load_fid_inception(path)
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        torch.testing.assert_close(loaded(x), net(x))
    assert inception_candidates(path) == [path]
    bad = dict(state)
    bad.pop("Mixed_6a.branch3x3.conv.weight")
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match=r"Mixed_6a\.branch3x3\.conv\.weight"):
        load_fid_inception(tmp_path / "bad.pth")


def test_evaluator_computes_fid_from_a_given_file(no_weights, tmp_path):
    from deliffas.models.metrics import Evaluator

    torch.manual_seed(1)
    path = tmp_path / "inception.pth"
    torch.save(FIDInceptionV3().state_dict(), path)
    ev = Evaluator(inception_path=path)
    gen = torch.Generator().manual_seed(2)
    mask = torch.ones(24, 24)
    for _ in range(2):
        gt = torch.rand(3, 24, 24, generator=gen)
        ev.add(torch.rand(3, 24, 24, generator=gen), gt, mask)
    s = ev.summary()
    assert s["fid"] is not None and s["fid"] > 0 and s["fid_reason"] is None and s["fid_images"] == 2


def test_matches_pytorch_fid_when_installed(monkeypatch):
    inception = pytest.importorskip(
        "pytorch_fid.inception",
        reason="pytorch-fid needs torchvision, whose wheels on this registry are CUDA builds that replace the "
               "CPU torch (and its ops fail to load against it): not installable here")
    torch.manual_seed(3)
    ours = FIDInceptionV3()

    def patched():  # pytorch-fid's fid_inception_v3 with our random weights instead of the download
        net = inception._inception_v3(num_classes=1008, aux_logits=False, weights=None)
        net.Mixed_5b = inception.FIDInceptionA(192, pool_features=32)
        net.Mixed_5c = inception.FIDInceptionA(256, pool_features=64)
        net.Mixed_5d = inception.FIDInceptionA(288, pool_features=64)
        net.Mixed_6b = inception.FIDInceptionC(768, channels_7x7=128)
        net.Mixed_6c = inception.FIDInceptionC(768, channels_7x7=160)
        net.Mixed_6d = inception.FIDInceptionC(768, channels_7x7=160)
        net.Mixed_6e = inception.FIDInceptionC(768, channels_7x7=192)
        net.Mixed_7b = inception.FIDInceptionE_1(1280)
        net.Mixed_7c = inception.FIDInceptionE_2(2048)
        missing, _ = net.load_state_dict(ours.state_dict(), strict=False)
        assert set(missing) <= {"fc.weight", "fc.bias"}
        return net

    monkeypatch.setattr(inception, "fid_inception_v3", patched)
    theirs = inception.InceptionV3([3]).eval()
    x = torch.rand(2, 3, 64, 48)
    with torch.no_grad():
        torch.testing.assert_close(ours(x), theirs(x)[0].flatten(1), rtol=1e-4, atol=1e-5)
