"""Training losses: foreground L1, the VGG-16 perceptual loss (whole image or patches) and the
step loss that combines them (:func:`step_loss`, used by the plain and the ray-chunked training step).

Paper section 3.4: ``L = lambda_1 L_1 + lambda_perc L_perc`` with a VGG-16 perceptual loss
(Johnson et al.) on the entire rendered image; the appendix ablates 32 x 32 patches instead.
The released code used VGG-19 ``block3_conv1`` (formats doc 3.7); we follow the paper's VGG-16.
:class:`PerceptualLoss` takes the backbone from :func:`deliffas.models.vgg.load_vgg16_weights`
(ImageNet weights, or the explicit seeded random option), so which one was used is recorded.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Literal, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from deliffas.models.vgg import VGG16_LAYERS, BackboneName, BackboneRecord, VGG16Features, load_vgg16_weights

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "l1_foreground", "PerceptualLoss", "foreground_patches", "StepLoss",
           "SaturationTerm", "saturation_penalty", "step_loss"]

logger = logging.getLogger(__name__)

#: ImageNet RGB mean / std used by torchvision's VGG-16 (inputs in [0, 1]).
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def l1_foreground(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error over foreground pixels and channels (formats doc 3.7).

    Args:
        pred: (..., ) float, e.g. (N, 3) ray colours or (B, 3, H, W) images.
        target: same shape as ``pred``.
        mask: foreground weights in [0, 1] broadcastable to ``pred`` (e.g. (N, 1) or
            (B, 1, H, W)); None = every element.

    Returns:
        () ``sum(mask |pred - target|) / sum(mask)`` over the broadcast shape; 0 (still
        differentiable) when the mask is empty.
    """
    if pred.shape != target.shape:
        raise ValueError(f"l1_foreground: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ")
    diff = (pred - target).abs()
    if mask is None:
        return diff.mean()
    try:
        weights = torch.broadcast_to(mask.to(diff.dtype), diff.shape)
    except RuntimeError as exc:
        raise ValueError(
            f"l1_foreground: mask {tuple(mask.shape)} does not broadcast to pred {tuple(pred.shape)}"
        ) from exc
    return (diff * weights).sum() / weights.sum().clamp_min(1.0)


def foreground_patches(
    mask: torch.Tensor | None,
    image_hw: tuple[int, int],
    batch: int,
    patch_size: int,
    num_patches: int,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Random patch positions centred inside each image's foreground bounding box.

    Centres are drawn uniformly over the integer pixels of the bounding box of ``mask > 0.5``
    (the whole image when the mask is None or empty); each patch is then shifted to lie inside
    the image.

    Args:
        mask: (B, 1, H, W) or (B, H, W) foreground mask, or None.
        image_hw: (H, W).
        batch: B.
        patch_size: P, side of the square patch (<= H and W).
        num_patches: K patches per image.
        generator: CPU ``torch.Generator`` for reproducible draws (None = global RNG).

    Returns:
        (B, K, 2) long, (top, left) of each patch, on CPU.
    """
    height, width = image_hw
    if patch_size > height or patch_size > width:
        raise ValueError(f"foreground_patches: patch_size {patch_size} exceeds the image size {height} x {width}")
    boxes = torch.tensor([[0, 0, height - 1, width - 1]] * batch, dtype=torch.long)  # (B, 4) y0 x0 y1 x1
    if mask is not None:
        fg = (mask.reshape(batch, height, width) > 0.5).cpu()
        rows, cols = fg.any(dim=2), fg.any(dim=1)  # (B, H), (B, W)
        for b in range(batch):
            if rows[b].any():
                r = rows[b].nonzero().squeeze(1)
                c = cols[b].nonzero().squeeze(1)
                boxes[b] = torch.stack([r[0], c[0], r[-1], c[-1]])
    u = torch.rand(batch, num_patches, 2, generator=generator)  # (B, K, 2)
    lo = boxes[:, None, :2].to(torch.float64)
    span = (boxes[:, None, 2:] - boxes[:, None, :2] + 1).to(torch.float64)
    centres = (lo + torch.floor(u.to(torch.float64) * span)).long()  # (B, K, 2)
    top_left = centres - patch_size // 2
    limits = torch.tensor([height - patch_size, width - patch_size])
    return torch.minimum(top_left.clamp_min(0), limits)


def _crop(images: torch.Tensor, top_left: torch.Tensor, patch_size: int) -> torch.Tensor:
    """Gather patches: images (B, 3, H, W), top_left (B, K, 2) -> (B K, 3, P, P)."""
    batch, num = top_left.shape[:2]
    offs = torch.arange(patch_size)
    rows = (top_left[..., 0:1] + offs).reshape(batch * num, patch_size).to(images.device)  # (BK, P)
    cols = (top_left[..., 1:2] + offs).reshape(batch * num, patch_size).to(images.device)  # (BK, P)
    b_idx = torch.arange(batch, device=images.device).repeat_interleave(num)  # (BK,)
    patches = images[b_idx[:, None, None], :, rows[:, :, None], cols[:, None, :]]  # (BK, P, P, 3)
    return patches.permute(0, 3, 1, 2)


class PerceptualLoss(nn.Module):
    """Feature-reconstruction loss on frozen VGG-16 activations (Johnson et al. 2016).

    ``loss = sum_l w_l * mean((phi_l(pred) - phi_l(target))^2)`` with ``w_l = 1 / #layers``,
    on ImageNet-normalised images. The backbone is frozen (``requires_grad`` False, kept in eval
    mode); gradients flow to ``pred``.

    Args:
        backbone: a VGG-16 trunk (see :func:`deliffas.models.vgg.load_vgg16_weights`).
        layers: ReLU layers compared (names of :data:`deliffas.models.vgg.VGG16_LAYERS`).
        mode: ``"image"``: whole images (the paper); ``"patch"``: random ``patch_size`` crops
            centred in the foreground bounding box (the appendix ablation).
        patch_size: patch side P (32 in the paper's ablation).
        num_patches: patches per image in patch mode.
        record: which backbone this is (kept for run records), or None.
    """

    def __init__(
        self,
        backbone: VGG16Features,
        layers: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_3", "relu4_3"),
        mode: Literal["image", "patch"] = "image",
        patch_size: int = 32,
        num_patches: int = 8,
        record: BackboneRecord | None = None,
    ) -> None:
        super().__init__()
        unknown = [name for name in layers if name not in VGG16_LAYERS]
        if unknown or not layers:
            raise ValueError(f"PerceptualLoss: unknown or no layers {unknown or layers}; known: {sorted(VGG16_LAYERS)}")
        if mode not in ("image", "patch"):
            raise ValueError(f"PerceptualLoss: mode must be 'image' or 'patch', got {mode!r}")
        if patch_size < 1 or num_patches < 1:
            raise ValueError(f"PerceptualLoss: patch_size and num_patches must be >= 1, got {patch_size}, {num_patches}")
        self.backbone = backbone
        for p in self.backbone.parameters():
            p.requires_grad_(False)
        self.backbone.eval()
        self.layers = tuple(layers)
        self.mode = mode
        self.patch_size = int(patch_size)
        self.num_patches = int(num_patches)
        self.record = record
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    @classmethod
    def from_source(
        cls,
        source: BackboneName,
        *,
        path: str | os.PathLike | None = None,
        seed: int = 0,
        **kwargs,
    ) -> "PerceptualLoss":
        """Build the loss with :func:`load_vgg16_weights` (``source``, ``path``, ``seed``); ``.record`` says which."""
        backbone, record = load_vgg16_weights(source, path=path, seed=seed)
        return cls(backbone, record=record, **kwargs)

    def train(self, mode: bool = True) -> "PerceptualLoss":
        """Switch the module's mode; the backbone always stays in eval mode."""
        super().train(mode)
        self.backbone.eval()
        return self

    def forward(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Perceptual distance of two image batches.

        Args:
            pred: (B, 3, H, W) float in [0, 1], rendered images (composited as the targets).
            target: (B, 3, H, W) float in [0, 1].
            mask: (B, 1, H, W) or (B, H, W) foreground mask; used only in patch mode to place
                patches (None = anywhere in the image).
            generator: CPU generator for the patch positions (patch mode).

        Returns:
            () scalar loss.
        """
        if pred.dim() != 4 or pred.shape[1] != 3 or pred.shape != target.shape:
            raise ValueError(
                f"PerceptualLoss: expected pred and target of shape (B, 3, H, W), got {tuple(pred.shape)}, "
                f"{tuple(target.shape)}"
            )
        if self.mode == "patch":
            top_left = foreground_patches(
                mask, (pred.shape[2], pred.shape[3]), pred.shape[0], self.patch_size, self.num_patches, generator
            )
            pred = _crop(pred, top_left, self.patch_size)
            target = _crop(target, top_left, self.patch_size)
        mean = self.mean.to(pred.dtype)
        std = self.std.to(pred.dtype)
        feats_pred = self.backbone((pred - mean) / std, self.layers)
        with torch.no_grad():
            feats_target = self.backbone((target - mean) / std, self.layers)
        loss = pred.new_zeros(())
        for name in self.layers:
            loss = loss + F.mse_loss(feats_pred[name], feats_target[name])
        return loss / len(self.layers)


@dataclass(frozen=True)
class StepLoss:
    """The loss of one training step and its terms (paper section 3.4: L = L1 + w L_perc)."""

    loss: torch.Tensor
    """() the value to differentiate: ``l1 + weight * perceptual``."""
    l1: torch.Tensor
    """() L1 over the shaded rays' values (or this chunk's share of it)."""
    perceptual: torch.Tensor | None = None
    """() perceptual distance of the images, or None when not computed."""

    def terms(self) -> dict[str, float]:
        """``{"loss", "l1"[, "perceptual"]}`` as floats (for logs)."""
        out = {"loss": float(self.loss.detach()), "l1": float(self.l1.detach())}
        if self.perceptual is not None:
            out["perceptual"] = float(self.perceptual.detach())
        return out


def saturation_penalty(logits: Sequence[torch.Tensor], margin: float) -> torch.Tensor:
    """Penalty on feature maps driven to the rails of their sigmoid: sum over maps of mean(relu(|s| - margin)^2).

    A U-Net's features are sigmoid(s); a map whose logits s sit far out has no gradient left, and
    the light field cannot pull it back (one seed of the ``realtime`` preset stalled that way with 98 %
    of its features at the rails, 5 dB below the others; docs/performance.md). The penalty is zero
    inside ``[-margin, margin]`` (margin 4: features within 0.018 of a rail are penalised).

    Args:
        logits: the maps' sigmoid inputs (``DeliffasModel.feature_logits()``), any shapes.
        margin: |s| allowed without penalty (> 0).

    Returns:
        () the penalty (0 for no maps).
    """
    if margin <= 0:
        raise ValueError(f"saturation_penalty: margin must be > 0, got {margin}")
    terms = [_BeyondMargin.apply(s, margin) for s in logits]
    return torch.stack(terms).sum() if terms else torch.zeros(())


class _BeyondMargin(torch.autograd.Function):
    """mean(relu(|s| - m)^2) with its gradient 2 (s - clamp(s, -m, m)) / numel, in the map's own memory layout.

    relu(|s| - m) sign(s) equals s - clamp(s, -m, m), torch's softshrink: the forward writes it in one pass and
    reads it once more (a dot product), the backward scales it in one. The autograd of the composed expression
    takes a dozen passes, several of them mixing a channels-last map with an expanded gradient (a slow strided
    path)."""

    @staticmethod
    def forward(ctx, s: torch.Tensor, margin: float) -> torch.Tensor:
        beyond = F.softshrink(s, margin)  # s - clamp(s, -m, m) in one pass
        ctx.save_for_backward(beyond)
        flat = _flat_view(beyond)
        return torch.dot(flat, flat) / max(s.numel(), 1)  # the sum of squares in one read

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (beyond,) = ctx.saved_tensors
        return beyond * (2 * grad / max(beyond.numel(), 1)), None


def _flat_view(t: torch.Tensor) -> torch.Tensor:
    """A dense tensor's elements as one vector in its memory order: a view for contiguous and channels-last
    maps."""
    if t.dim() == 4 and not t.is_contiguous() and t.is_contiguous(memory_format=torch.channels_last):
        return t.permute(0, 2, 3, 1).reshape(-1)
    return t.reshape(-1)


@dataclass(frozen=True)
class SaturationTerm:
    """A run's saturation penalty: ``weight`` x :func:`saturation_penalty` of the model's U-Net logits."""

    weight: float
    """Its weight in the step loss (> 0)."""
    margin: float = 4.0
    """|logit| allowed without penalty."""

    def __post_init__(self) -> None:
        if not (self.weight > 0 and self.margin > 0):
            raise ValueError(f"SaturationTerm: weight and margin must be > 0, got {self.weight}, {self.margin}")

    def penalty(self, model) -> torch.Tensor:
        """() the unweighted penalty of ``model`` (a DeliffasModel) after its training forward: the penalties its
        U-Nets computed with their sigmoid (``DeliffasModel.track_saturation(margin)`` before the forward), else
        :func:`saturation_penalty` of their logits."""
        terms = model.feature_penalties(self.margin)
        if terms is None:
            return saturation_penalty(model.feature_logits(), self.margin)
        return torch.stack(terms).sum() if terms else torch.zeros(())


def step_loss(
    pred_rays: torch.Tensor,
    target_rays: torch.Tensor,
    *,
    num_values: int | None = None,
    perceptual: nn.Module | None = None,
    weight: float = 0.0,
    pred_images: torch.Tensor | None = None,
    target_images: torch.Tensor | None = None,
    masks: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> StepLoss:
    """The training loss of shaded rays (L1) plus, when ``perceptual`` and ``weight > 0``, the
    perceptual term on the images they were painted into.

    Args:
        pred_rays: (N, 3) shaded colours.
        target_rays: (N, 3) their targets (images composited on black, at the rays' pixels).
        num_values: denominator of the L1 sum; default ``pred_rays.numel()`` (the mean). A chunk
            of a step's rays passes the step's 3 N_total, so the chunks' L1 terms add up to the
            step's.
        perceptual: a :class:`PerceptualLoss`, or None (L1 only).
        weight: w of the perceptual term.
        pred_images: (K, H, W, 3) in [0, 1] (needed with ``perceptual``).
        target_images: (K, H, W, 3) in [0, 1] (needed with ``perceptual``).
        masks: (K, H, W) foreground masks (patch placement in patch mode).
        generator: CPU generator for the patch positions.
    """
    if pred_rays.shape != target_rays.shape:
        raise ValueError(f"step_loss: pred_rays {tuple(pred_rays.shape)} and target_rays "
                         f"{tuple(target_rays.shape)} differ")
    l1 = (pred_rays - target_rays).abs().sum() / (pred_rays.numel() if num_values is None else num_values)
    if perceptual is None or weight <= 0:
        return StepLoss(l1, l1)
    if pred_images is None or target_images is None:
        raise ValueError("step_loss: the perceptual term needs pred_images and target_images")
    p = perceptual(pred_images.permute(0, 3, 1, 2), target_images.permute(0, 3, 1, 2), masks, generator=generator)
    return StepLoss(l1 + weight * p, l1, p)
