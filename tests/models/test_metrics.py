"""Tests of deliffas.models.metrics: protocol steps, PSNR, SSIM (vs a scipy oracle), LPIPS status."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from deliffas.models.metrics import (
    FID_UNAVAILABLE_REASON,
    LPIPS,
    Evaluator,
    composite_on_white,
    crop_window,
    eval_mask,
    load_lpips_linear_weights,
    mae,
    mse,
    perceptual_metrics_status,
    prepare_pair,
    psnr,
    ssim,
)

LPIPS_CHANNELS = (64, 128, 256, 512, 512)


def skimage_style_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """scikit-image's algorithm (gaussian_weights, sigma 1.5, population covariance), via scipy."""
    from scipy.ndimage import gaussian_filter

    values = []
    for c in range(x.shape[0]):
        a, b = x[c].astype(np.float64), y[c].astype(np.float64)
        f = lambda z: gaussian_filter(z, sigma=1.5, truncate=3.5, mode="reflect")  # noqa: E731
        ux, uy = f(a), f(b)
        vx, vy, vxy = f(a * a) - ux * ux, f(b * b) - uy * uy, f(a * b) - ux * uy
        c1, c2 = 0.01**2, 0.03**2
        s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux**2 + uy**2 + c1) * (vx + vy + c2))
        values.append(s[5:-5, 5:-5].mean())
    return float(np.mean(values))


def test_psnr_known_values():
    gt = torch.full((3, 20, 20), 0.5, dtype=torch.float64)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-6)
    assert psnr(gt + 0.01, gt) == pytest.approx(40.0, abs=1e-4)
    assert psnr(gt, gt) == math.inf
    assert psnr(gt, gt, max_db=60.0) == 60.0
    assert mse(gt + 0.1, gt) == pytest.approx(0.01)
    assert mae(gt - 0.2, gt) == pytest.approx(0.2)
    with pytest.raises(ValueError, match="differ"):
        psnr(gt, gt[:, :10])


def test_ssim_identical_and_monotone_in_noise():
    gen = torch.Generator().manual_seed(0)
    gt = torch.rand(3, 40, 36, generator=gen)
    assert ssim(gt, gt) == pytest.approx(1.0, abs=1e-12)
    noise = torch.randn(3, 40, 36, generator=gen)
    scores = [ssim((gt + s * noise).clamp(0, 1), gt) for s in (0.01, 0.05, 0.2, 0.5)]
    assert all(a > b for a, b in zip(scores, scores[1:])), scores
    with pytest.raises(ValueError, match="at least 11"):
        ssim(gt[:, :10], gt[:, :10])


def test_ssim_matches_scikit_image_algorithm():
    gen = torch.Generator().manual_seed(1)
    gt = torch.rand(3, 33, 29, generator=gen, dtype=torch.float64)
    pred = (gt + 0.1 * torch.randn(3, 33, 29, generator=gen, dtype=torch.float64)).clamp(0, 1)
    assert ssim(pred, gt) == pytest.approx(skimage_style_ssim(pred.numpy(), gt.numpy()), abs=1e-12)


def test_eval_mask_threshold_and_erosion():
    mask = torch.zeros(20, 20)
    mask[5:15, 5:15] = 0.8
    mask[0, 0] = 0.5  # not > 0.5
    out = eval_mask(mask)
    expected = torch.zeros(20, 20, dtype=torch.bool)
    expected[7:13, 7:13] = True
    assert torch.equal(out, expected)
    assert eval_mask(torch.ones(9, 9)).all()  # the image border does not erode
    assert torch.equal(eval_mask(mask, erode=1), mask > 0.5)


def test_composite_on_white():
    image = torch.zeros(3, 4, 4)
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[1:3, 1:3] = True
    out = composite_on_white(image, mask)
    assert (out[:, 1:3, 1:3] == 0).all() and out.sum() == 3 * 12


def _white_with_box(h: int, w: int, rows: slice, cols: slice) -> torch.Tensor:
    img = torch.ones(3, h, w)
    img[:, rows, cols] = 0.2
    return img


def test_crop_window_centres_and_shifts():
    assert crop_window(_white_with_box(1285, 940, slice(500, 701), slice(400, 501))) == (300, 202, 600, 496)
    assert crop_window(_white_with_box(700, 600, slice(100, 200), slice(50, 150))) == (0, 0, 600, 496)
    assert crop_window(_white_with_box(700, 600, slice(600, 700), slice(500, 600))) == (100, 104, 600, 496)
    assert crop_window(_white_with_box(40, 30, slice(1, 5), slice(1, 5))) == (0, 0, 40, 30)
    assert crop_window(torch.ones(3, 700, 600)) == (50, 52, 600, 496)


def test_prepare_pair_resizes_masks_and_crops():
    gen = torch.Generator().manual_seed(2)
    gt = torch.rand(3, 640, 520, generator=gen) * 0.9
    mask = torch.zeros(640, 520)
    mask[100:500, 100:400] = 1
    pred = torch.rand(3, 320, 260, generator=gen)
    p, g = prepare_pair(pred, gt, mask)
    assert p.shape == g.shape == (3, 600, 496)
    top, left, _, _ = crop_window(composite_on_white(gt, eval_mask(mask)))
    background = ~eval_mask(mask)[top : top + 600, left : left + 496]
    assert (p[:, background] == 1).all() and (g[:, background] == 1).all()
    assert (g[:, ~background] < 1).all()
    with pytest.raises(ValueError, match="mask"):
        prepare_pair(pred, gt, mask[:10])


def test_status_without_weights(no_weights):
    status = perceptual_metrics_status()
    assert status["lpips"] is None and "VGG-16 ImageNet" in status["lpips_reason"]
    assert "LPIPS v0.1" in status["lpips_reason"]
    assert status["fid"] is None and status["fid_reason"] == FID_UNAVAILABLE_REASON
    given = perceptual_metrics_status(inception_path="/x/pt_inception.pth")
    assert given["fid"] is None and "not found at /x/pt_inception.pth" in given["fid_reason"]


def test_evaluator_reports_substitute_beside_unavailable_lpips(no_weights):
    gen = torch.Generator().manual_seed(3)
    gt = torch.rand(3, 48, 40, generator=gen)
    mask = torch.zeros(48, 40)
    mask[8:40, 8:32] = 1
    ev = Evaluator()
    same = ev.add(gt, gt, mask)
    assert same.psnr == math.inf and same.ssim == pytest.approx(1.0) and same.lpips is None
    assert same.lpips_random_vgg16 == 0.0
    other = ev.add((gt + 0.2 * torch.randn(3, 48, 40, generator=gen)).clamp(0, 1), gt, mask)
    assert other.lpips_random_vgg16 > 0 and other.psnr < 40
    summary = ev.summary()
    assert summary["num_images"] == 2 and summary["lpips"] is None and summary["fid"] is None
    assert summary["lpips_reason"] and summary["fid_reason"] == FID_UNAVAILABLE_REASON
    assert summary["lpips_random_vgg16"] == pytest.approx(other.lpips_random_vgg16 / 2)
    assert summary["lpips_random_vgg16_backbone"]["name"] == "vgg16-random"


def test_evaluator_quantizes_to_8_bit(no_weights):
    gt = torch.full((3, 24, 24), 0.5)
    pred = gt + 0.001  # below half an 8-bit step: identical once saved as PNG
    mask = torch.ones(24, 24)
    assert Evaluator(substitute_seed=1).add(pred, gt, mask).psnr == math.inf
    assert Evaluator(substitute_seed=1, quantize_8bit=False).add(pred, gt, mask).psnr == pytest.approx(60.0, abs=0.01)


@pytest.fixture
def lpips_file(tmp_path):
    gen = torch.Generator().manual_seed(4)
    state = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=gen) for i, c in enumerate(LPIPS_CHANNELS)}
    path = tmp_path / "vgg.pth"
    torch.save(state, path)
    return path, state


def test_lpips_available_with_weights(no_weights, vgg_files, lpips_file):
    path, state = lpips_file
    status = perceptual_metrics_status(vgg16_path=vgg_files["pth"], lpips_path=path)
    assert status["lpips"] is not None and status["lpips_reason"] is None
    weights = load_lpips_linear_weights(path)
    assert [w.shape for w in weights] == [(c,) for c in LPIPS_CHANNELS]
    ev = Evaluator(vgg16_path=vgg_files["pth"], lpips_path=path)
    gen = torch.Generator().manual_seed(5)
    gt = torch.rand(3, 32, 32, generator=gen)
    result = ev.add(torch.rand(3, 32, 32, generator=gen), gt, torch.ones(32, 32))
    assert result.lpips is not None and result.lpips > 0
    assert ev.summary()["lpips"] == pytest.approx(result.lpips)


def test_lpips_formula(random_backbone):
    backbone, _ = random_backbone
    gen = torch.Generator().manual_seed(6)
    weights = [torch.rand(c, generator=gen) for c in LPIPS_CHANNELS]
    net = LPIPS(backbone, weights)
    x, y = torch.rand(2, 3, 16, 16, generator=gen), torch.rand(2, 3, 16, 16, generator=gen)
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
    names = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
    fx = backbone(((2 * x - 1) - shift) / scale, names)
    fy = backbone(((2 * y - 1) - shift) / scale, names)
    expected = 0
    for w, name in zip(weights, names):
        a = fx[name] / (fx[name].norm(dim=1, keepdim=True) + 1e-10)
        b = fy[name] / (fy[name].norm(dim=1, keepdim=True) + 1e-10)
        expected = expected + (w.view(1, -1, 1, 1) * (a - b) ** 2).sum(1).mean((1, 2))
    torch.testing.assert_close(net(x, y), expected)
    assert torch.allclose(net(x, x), torch.zeros(2))


def test_lpips_file_layout_checked(tmp_path):
    path = tmp_path / "wrong.pth"
    torch.save({"lin0.weight": torch.rand(1, 64, 1, 1)}, path)
    with pytest.raises(ValueError, match=r"lin0\.model\.1\.weight"):
        load_lpips_linear_weights(path)
