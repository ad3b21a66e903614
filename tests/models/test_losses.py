"""Tests of deliffas.models.losses."""

from __future__ import annotations

import pytest
import torch

from deliffas.models.losses import PerceptualLoss, SaturationTerm, foreground_patches, l1_foreground, saturation_penalty


def test_l1_foreground_values():
    pred = torch.zeros(4, 3)
    target = torch.tensor([[1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [9.0, 9.0, 9.0], [2.0, 2.0, 2.0]])
    mask = torch.tensor([[1.0], [1.0], [0.0], [0.0]])
    assert float(l1_foreground(pred, target, mask)) == pytest.approx(0.75)
    assert float(l1_foreground(pred, target)) == pytest.approx((1 + 0.5 + 9 + 2) / 4)
    images = torch.zeros(2, 3, 4, 4)
    assert float(l1_foreground(images, images + 1, torch.ones(2, 1, 4, 4))) == pytest.approx(1.0)


def test_l1_empty_mask_and_errors():
    pred = torch.rand(5, 3, requires_grad=True)
    loss = l1_foreground(pred, torch.rand(5, 3), torch.zeros(5, 1))
    assert float(loss.detach()) == 0.0
    loss.backward()
    assert pred.grad is not None
    with pytest.raises(ValueError, match="differ"):
        l1_foreground(pred, torch.rand(5, 2))
    with pytest.raises(ValueError, match="broadcast"):
        l1_foreground(pred, torch.rand(5, 3), torch.ones(4, 1))


@pytest.fixture(params=["vgg16-random", "vgg16-imagenet"])
def perceptual(request, vgg_files):
    """Both perceptual options (imagenet loaded from the fake file: same code path as the real one)."""
    path = vgg_files["pth"] if request.param == "vgg16-imagenet" else None
    return PerceptualLoss.from_source(request.param, path=path)


@pytest.mark.parametrize("mode", ["image", "patch"])
def test_perceptual_gradients_finite(perceptual, mode):
    loss_fn = PerceptualLoss(perceptual.backbone, mode=mode, patch_size=16, num_patches=2, record=perceptual.record)
    gen = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 3, 32, 32, generator=gen).requires_grad_(True)
    target = torch.rand(2, 3, 32, 32, generator=gen)
    mask = torch.zeros(2, 1, 32, 32)
    mask[:, :, 8:24, 8:24] = 1
    loss = loss_fn(pred, target, mask, generator=torch.Generator().manual_seed(1))
    assert loss.dim() == 0 and float(loss.detach()) > 0
    loss.backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    assert all(p.grad is None for p in loss_fn.backbone.parameters())
    assert float(loss_fn(target, target, mask, generator=torch.Generator().manual_seed(1))) == 0.0


def test_perceptual_records_backbone(perceptual, vgg_files):
    assert perceptual.record is not None
    if perceptual.record.name == "vgg16-imagenet":
        assert perceptual.record.path == str(vgg_files["pth"])
    else:
        assert perceptual.record.seed == 0


def test_backbone_stays_frozen_and_eval(random_backbone):
    loss_fn = PerceptualLoss(random_backbone[0])
    loss_fn.train()
    assert loss_fn.training and not loss_fn.backbone.training
    assert all(not p.requires_grad for p in loss_fn.backbone.parameters())
    assert "mean" not in loss_fn.state_dict()


def test_patches_lie_in_foreground_box():
    mask = torch.zeros(3, 64, 48)
    mask[0, 20:30, 10:20] = 1
    mask[1, 0:5, 40:48] = 1  # near a corner: patches must be shifted inside the image
    top_left = foreground_patches(mask, (64, 48), 3, 16, 50, torch.Generator().manual_seed(0))
    assert top_left.shape == (3, 50, 2)
    assert (top_left >= 0).all() and (top_left[..., 0] <= 48).all() and (top_left[..., 1] <= 32).all()
    centres = top_left[0] + 8
    assert (centres[:, 0] >= 20).all() and (centres[:, 0] <= 29).all()
    assert (centres[:, 1] >= 10).all() and (centres[:, 1] <= 19).all()
    assert (top_left[1, :, 0] == 0).all() and (top_left[1, :, 1] == 32).all()
    again = foreground_patches(mask, (64, 48), 3, 16, 50, torch.Generator().manual_seed(0))
    assert torch.equal(top_left, again)
    # the empty mask (image 2) spreads over the whole image
    assert top_left[2, :, 0].max() > 30 and top_left[2, :, 0].min() < 10


def test_patch_crop_content(random_backbone):
    loss_fn = PerceptualLoss(random_backbone[0], mode="patch", patch_size=8, num_patches=1)
    image = torch.zeros(1, 3, 32, 32)
    mask = torch.zeros(1, 32, 32)
    mask[0, 10:12, 20:22] = 1
    pred = image.clone()
    pred[:, :, 0:3, 0:3] = 1.0  # differs only far from the foreground: patch loss must ignore it
    assert float(loss_fn(pred, image, mask, generator=torch.Generator().manual_seed(0))) == 0.0
    pred[:, :, 10, 20] = 1.0
    assert float(loss_fn(pred, image, mask, generator=torch.Generator().manual_seed(0))) > 0.0


def test_perceptual_errors(random_backbone, unchecked):
    with unchecked(), pytest.raises(ValueError, match="mode"):
        PerceptualLoss(random_backbone[0], mode="tile")  # type: ignore[arg-type]
    with unchecked(), pytest.raises(ValueError, match="layers"):
        PerceptualLoss(random_backbone[0], layers=("relu9_9",))
    loss_fn = PerceptualLoss(random_backbone[0], mode="patch", patch_size=64)
    with unchecked(), pytest.raises(ValueError, match="patch_size"):
        loss_fn(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32))


def test_saturation_penalty_pulls_logits_back_inside_the_margin():
    """Zero inside [-margin, margin]; outside, its gradient points back towards the margin."""
    s = torch.tensor([[-6.0, -4.0, 0.0, 3.9, 5.0]], requires_grad=True)
    p = saturation_penalty([s], 4.0)
    assert float(p) == pytest.approx((2.0**2 + 1.0**2) / 5)
    p.backward()
    assert s.grad[0].tolist() == pytest.approx([-0.8, 0, 0, 0, 0.4])  # descent moves -6 up and 5 down
    assert float(saturation_penalty([], 4.0)) == 0.0
    two = saturation_penalty([torch.full((2, 3), 5.0), torch.zeros(4)], 4.0)
    assert float(two) == pytest.approx(1.0)  # a mean per map, summed over maps
    with pytest.raises(ValueError, match="margin must be > 0"):
        saturation_penalty([s], 0.0)
    with pytest.raises(ValueError, match="weight and margin must be > 0"):
        SaturationTerm(0.0)


def test_unet_keeps_the_logits_of_its_training_forward_only():
    from deliffas.models.unet import UNet, UNetConfig

    net = UNet(UNetConfig(in_channels=3, out_channels=2, base_channels=4, max_channels=8), 16)
    x = torch.randn(1, 3, 16, 16)
    y = net(x)
    assert net.last_logits.shape == (1, 2, 16, 16)
    torch.testing.assert_close(torch.sigmoid(net.last_logits), y)
    with torch.no_grad():
        net(x)
    assert net.last_logits is None  # nothing held after inference


@pytest.mark.parametrize("side", [16, 256])  # the final layer as a matrix product, and by oneDNN in channels_last
def test_unet_training_logits_are_its_final_layer_doubled_exactly(side):
    """The factor 2 of sigmoid(2 y) sits in the final layer's weights during training: the same values as
    doubling its output (exact in floating point), without the pass over the map."""
    from deliffas.models.unet import UNet, UNetConfig

    torch.manual_seed(0)
    net = UNet(UNetConfig(in_channels=3, out_channels=4, base_channels=4, max_channels=8), side)
    x = torch.randn(1, 3, side, side)
    net(x)
    skips, h = [], x
    for block in net.down:
        h = block(h)
        skips.append(h)
    h = skips.pop()
    for block in net.up:
        h = torch.cat([block(h), skips.pop()], dim=1)
    assert torch.equal(net.last_logits, 2.0 * net.final(h))
    with pytest.raises(ValueError, match="scale takes no epilogue"):
        net.final(h, scale=2.0, output_size=[2 * side, 2 * side])


@pytest.mark.parametrize("channels_last", [False, True])
def test_saturation_penalty_value_and_gradient_equal_the_composed_expression(channels_last):
    g = torch.Generator().manual_seed(0)
    s = (torch.randn(1, 5, 8, 8, generator=g) * 4).requires_grad_()
    if channels_last:
        s = s.detach().contiguous(memory_format=torch.channels_last).requires_grad_()
    ref = s.detach().clone().requires_grad_()
    (3.0 * saturation_penalty([s], 4.0)).backward()
    expected = torch.relu(ref.abs() - 4.0).square().mean()
    (3.0 * expected).backward()
    assert torch.allclose(saturation_penalty([s.detach()], 4.0), expected.detach(), rtol=1e-6)
    assert torch.allclose(s.grad, ref.grad, rtol=1e-6, atol=1e-9)
    assert s.grad.is_contiguous(memory_format=torch.channels_last) == channels_last
