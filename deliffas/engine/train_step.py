"""One optimisation step on one frame: U-Nets once, every shaded ray of the K images, one loss.

The loss is :func:`deliffas.models.losses.step_loss` on the shaded rays (and, in stage 2, on the
images they are painted into). With ``ray_chunk`` the light field is differentiated chunk by chunk
(same gradient, bounded memory; docs/reliability.md).
"""

from __future__ import annotations

import math

import torch

from deliffas.engine.rays import RayBatch, paint_images, ray_query, stack_rays
from deliffas.engine.samples import FrameSample, composite_target
from deliffas.engine.timing import StageTimer
from deliffas.models.deliffas import DeliffasModel, FrameFeatures
from deliffas.models.losses import SaturationTerm, step_loss
from deliffas.models.ray_query import RayQuery

__all__ = ["train_step", "render_sample_images", "balance_weight", "MLP_BLOCK"]

MLP_BLOCK = 4096
"""Rays per light-field block of a training step with a per-ray loss (L1 only): the features of
every ray are sampled in one graph, then the MLP runs forward and backward on each block of this
many rays while its activations are still in the CPU's cache, and the blocks' feature gradients go
through the sampling and the U-Nets in one backward. The gradient is the one-graph gradient up to
float summation order; peak memory is lower (one block's MLP activations)."""


def _rays(model: DeliffasModel, sample: FrameSample, device: torch.device) -> tuple[RayBatch, RayQuery]:
    """The sample's rays of all K cameras (one frame: batch row 0) and the model's query of them."""
    batch = stack_rays(sample.rays, [0] * sample.num_cameras).to(device)
    return batch, ray_query(batch, model.spec)


def _targets(sample: FrameSample, batch: RayBatch, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The training target images (K, H, W, 3) and their values at the rays' pixels (N, 3)."""
    K, H, W = sample.images.shape[:3]
    target = composite_target(sample.images, sample.masks).to(device)
    return target, target.reshape(K, H * W, 3)[batch.image_index, batch.pixels]


def _target_rays(sample: FrameSample, batch: RayBatch, device: torch.device) -> torch.Tensor:
    """The training target's values at the rays' pixels (N, 3): ``_targets``' second value, with only those
    pixels composited (the same values)."""
    K, H, W = sample.images.shape[:3]
    at = (batch.image_index.cpu(), batch.pixels.cpu())
    colour = torch.as_tensor(sample.images).reshape(K, H * W, 3)[at]
    coverage = torch.as_tensor(sample.masks).reshape(K, H * W)[at]
    return composite_target(colour, coverage).to(device)


def _psnr(mse: float) -> float:
    return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")


def render_sample_images(model: DeliffasModel, sample: FrameSample, device: torch.device,
                         net: torch.nn.Module | None = None, timer: StageTimer | None = None,
                         chunk_size: int | None = None) -> torch.Tensor:
    """Images (K, H, W, 3) of the sample's cameras, background black; differentiable unless no_grad.

    ``net`` is the module called for the forward pass (the DDP wrapper during distributed
    training), by default the model itself. With a ``timer`` the stages are timed separately
    (``cnn`` encode, ``shade`` the light field, in chunks of ``chunk_size`` rays).
    """
    H, W = sample.images.shape[1:3]
    batch, query = _rays(model, sample, device)
    normals = sample.normal_maps(device)
    if timer is None and chunk_size is None:
        pred = (net or model)(*normals, query)
    else:
        timer = timer or StageTimer(device)
        with timer.stage("cnn"):
            features = model.encode(*normals)
        with timer.stage("shade"):
            pred = model.shade_chunked(features, query, chunk_size=chunk_size or 262144)
    return paint_images(pred, batch, sample.num_cameras, H, W)


def _chunked_backward(model: DeliffasModel, sample: FrameSample, device: torch.device,
                      perceptual: torch.nn.Module | None, perceptual_weight: float,
                      generator: torch.Generator | None, ray_chunk: int,
                      saturation: SaturationTerm | None) -> tuple[dict[str, float], float]:
    """Gradients of one step's loss, shading at most ``ray_chunk`` rays per graph (same gradient).

    The U-Nets run once and keep their graph; the light field's gradient w.r.t. the feature maps is
    accumulated chunk by chunk on detached copies and then pushed through the U-Nets in one
    backward. With a perceptual term, the step loss is differentiated once w.r.t. the rays'
    colours (rendered without a graph), and that gradient enters each chunk's backward. Returns
    the loss terms and the mean squared error over the shaded values.
    """
    K = sample.num_cameras
    H, W = sample.images.shape[1:3]
    batch, query = _rays(model, sample, device)
    features = model.encode(*sample.normal_maps(device))  # (1, C, S, S) maps with the U-Net graph
    leaves = FrameFeatures(inner=features.inner.detach().requires_grad_(),
                           outer=None if features.outer is None else features.outer.detach().requires_grad_(),
                           normals=features.normals)
    target, target_rays = _targets(sample, batch, device)  # (K, H, W, 3), (N, 3)
    n = batch.num_rays
    ray_grad = terms = None
    if perceptual is not None and perceptual_weight > 0:
        with torch.no_grad():
            pred_all = model.shade_chunked(leaves, query, chunk_size=ray_chunk).requires_grad_()
        loss = step_loss(pred_all, target_rays, perceptual=perceptual, weight=perceptual_weight,
                         pred_images=paint_images(pred_all, batch, K, H, W), target_images=target,
                         masks=torch.from_numpy(sample.masks).to(device), generator=generator)
        loss.loss.backward()
        ray_grad, terms = pred_all.grad, loss.terms()  # (N, 3): d loss / d colour of every ray
        del pred_all, loss
    l1_sum = sq_sum = 0.0
    for start in range(0, n, ray_chunk):
        sl = slice(start, start + ray_chunk)
        pred = model.shade(leaves, query[sl])
        if ray_grad is None:
            chunk = step_loss(pred, target_rays[sl], num_values=3 * n)
            chunk.loss.backward()
            l1_sum += float(chunk.l1.detach())
        else:
            pred.backward(ray_grad[sl])
        sq_sum += float((pred.detach() - target_rays[sl]).square().sum())
    roots = [(f, leaf.grad) for f, leaf in ((features.inner, leaves.inner), (features.outer, leaves.outer))
             if f is not None and leaf.grad is not None]
    out = _backward_below_mlp(model, roots, terms or {"loss": l1_sum, "l1": l1_sum}, saturation)
    return out, sq_sum / (3 * n)


def _backward_below_mlp(model: DeliffasModel, roots: list[tuple[torch.Tensor, torch.Tensor | None]],
                        terms: dict[str, float], saturation: SaturationTerm | None) -> dict[str, float]:
    """One backward through the sampling and the U-Nets from the light field's gradients ``roots``
    ((tensor, gradient) pairs), with the saturation penalty added; returns ``terms`` with it."""
    if saturation is not None:  # through the U-Nets' graph, with the light field's gradient
        penalty = saturation.penalty(model)
        roots = [*roots, (saturation.weight * penalty, None)]
        terms = {**terms, "saturation": float(penalty.detach())}
    if roots:
        torch.autograd.backward([f for f, _ in roots], [g for _, g in roots])
    return terms


def _blocked_backward(model: DeliffasModel, sample: FrameSample, device: torch.device, block: int,
                      saturation: SaturationTerm | None) -> tuple[dict[str, float], float]:
    """Gradients of one step's L1 loss with the light-field MLP run block by block (:data:`MLP_BLOCK`).

    Returns the loss terms and the mean squared error over the shaded values.
    """
    batch, query = _rays(model, sample, device)
    features = model.encode(*sample.normal_maps(device), joined=False)  # atlases sampled apart: no joined maps
    encoded, feats = model.gather_inputs(features, query)  # (N, E) without, (N, C) with a graph
    target_rays = _target_rays(sample, batch, device)
    n = batch.num_rays
    feature_grads, l1_sums, sq_sums = [], [], []
    for start in range(0, n, block):
        sl = slice(start, start + block)
        leaf = feats[sl].detach().requires_grad_()
        pred = model.mlp(encoded[sl], leaf)
        chunk = step_loss(pred, target_rays[sl], num_values=3 * n)
        chunk.loss.backward()
        l1_sums.append(chunk.l1.detach())
        sq_sums.append((pred.detach() - target_rays[sl]).square().sum())
        feature_grads.append(leaf.grad)
    # with frozen feature maps no parameter below the MLP needs a gradient: the blocks' backward was all
    roots = [(feats, torch.cat(feature_grads))] if feats.requires_grad else []
    l1_sum = float(torch.stack(l1_sums).sum())  # one read of the device's sums, after every block
    terms = _backward_below_mlp(model, roots, {"loss": l1_sum, "l1": l1_sum}, saturation)
    return terms, float(torch.stack(sq_sums).sum()) / (3 * n)


def train_step(model: DeliffasModel, sample: FrameSample, optimizer: torch.optim.Optimizer, device: torch.device,
               perceptual: torch.nn.Module | None = None, perceptual_weight: float = 0.0,
               net: torch.nn.Module | None = None, generator: torch.Generator | None = None,
               ray_chunk: int | None = None, saturation: SaturationTerm | None = None,
               mlp_block: int | None = MLP_BLOCK) -> dict[str, float]:
    """One optimisation step on one frame; returns the loss terms and the step's PSNR (on shaded rays).

    ``saturation`` adds its weighted penalty on the U-Nets' feature logits to the loss (logged as
    ``saturation``, unweighted; ``loss`` stays the image loss).

    ``ray_chunk`` bounds the rays shaded in one graph (single process only): the U-Nets run once,
    the light field chunk by chunk, and the gradient equals the unchunked one up to float
    summation order. Peak memory is then U-Nets + ``ray_chunk`` rays instead of every ray of the K
    images (docs/reliability.md).

    On the CPU, without ``ray_chunk``, a perceptual term or a DDP ``net``, the light field runs in
    blocks of ``mlp_block`` rays (:data:`MLP_BLOCK`; None: one graph over every ray), the same
    gradient up to float summation order. Other devices run one graph: blocks would only add kernel
    launches there (a 940 x 1285 step of 4 cameras is 221 blocks).

    A sample whose cameras shade no ray at all (every camera looks away from the subject, or the
    outer shell lies outside every image) has no pixel that depends on a parameter, and the mean L1
    over zero rays would be NaN: the step is skipped (no optimizer step; ``skipped`` = 1, losses 0,
    ``psnr_rays`` NaN). Under DistributedDataParallel the rank still runs a zero-loss backward and
    steps with the other ranks' averaged gradients, so no collective hangs and the replicas stay equal.
    """
    ddp = isinstance(net, torch.nn.parallel.DistributedDataParallel)
    if ray_chunk is not None and (ray_chunk < 1 or ddp):
        raise ValueError(f"ray_chunk must be >= 1 and needs a single process (got {ray_chunk}, DDP {ddp})")
    if mlp_block is not None and mlp_block < 1:
        raise ValueError(f"mlp_block must be >= 1 or None, got {mlp_block}")
    num_rays = sum(r.num_rays for r in sample.rays)
    if num_rays == 0 and not ddp:
        optimizer.zero_grad(set_to_none=True)
        return {"l1": 0.0, "loss": 0.0, "psnr_rays": float("nan"), "skipped": 1.0}
    model.train()
    model.track_saturation(None if saturation is None else saturation.margin)  # computed with the sigmoid
    optimizer.zero_grad(set_to_none=True)
    if ray_chunk is not None and num_rays > ray_chunk:
        out, mse = _chunked_backward(model, sample, device, perceptual, perceptual_weight, generator, ray_chunk,
                                     saturation)
    elif (mlp_block is not None and torch.device(device).type == "cpu" and num_rays and not ddp
          and not (perceptual is not None and perceptual_weight > 0)):
        out, mse = _blocked_backward(model, sample, device, mlp_block, saturation)
    else:
        out, mse = _one_graph_backward(model, sample, device, perceptual, perceptual_weight, net, generator,
                                       saturation)
    optimizer.step()
    return {**out, "skipped": 0.0 if num_rays else 1.0, "psnr_rays": _psnr(mse) if num_rays else float("nan")}


def _one_graph_backward(model: DeliffasModel, sample: FrameSample, device: torch.device,
                        perceptual: torch.nn.Module | None, perceptual_weight: float, net: torch.nn.Module | None,
                        generator: torch.Generator | None, saturation: SaturationTerm | None
                        ) -> tuple[dict[str, float], float]:
    """Forward and backward of every ray in one graph; the loss terms and the rays' mean squared error
    (NaN for a DDP rank with no ray, which backpropagates a zero loss that reaches every parameter)."""
    K = sample.num_cameras
    H, W = sample.images.shape[1:3]
    batch, query = _rays(model, sample, device)
    pred = (net or model)(*sample.normal_maps(device), query)  # (N, 3)
    target, target_rays = _targets(sample, batch, device)  # (K, H, W, 3), (N, 3)
    if not len(pred):  # DDP only: every gradient hook (all-reduce) must fire
        zero = pred.sum() * 0.0 + sum(p.sum() for p in model.parameters() if p.requires_grad) * 0.0
        zero.backward()
        return {"loss": 0.0, "l1": 0.0}, float("nan")
    # L1 over the rays the model paints (pixels outside the shell are background in both images,
    # up to person pixels the shell misses, which no parameter can change)
    pred_images = paint_images(pred, batch, K, H, W) if perceptual is not None and perceptual_weight > 0 else None
    loss = step_loss(pred, target_rays, perceptual=perceptual, weight=perceptual_weight, pred_images=pred_images,
                     target_images=target, masks=torch.from_numpy(sample.masks).to(device), generator=generator)
    out = loss.terms()
    total = loss.loss
    if saturation is not None:
        penalty = saturation.penalty(model)
        total = total + saturation.weight * penalty
        out["saturation"] = float(penalty.detach())
    total.backward()
    return out, float((pred.detach() - target_rays).square().mean())


def balance_weight(model: DeliffasModel, sample: FrameSample, device: torch.device,
                   perceptual: torch.nn.Module) -> float:
    """Perceptual weight making both loss terms equally large on this frame (paper: 'roughly the same').

    The L1 it matches is the one the step differentiates: the mean over the shaded rays
    (:func:`step_loss`), not over whole images. The images' background pixels outside the shell
    are 0 in both, so a whole-image L1 is smaller by the rays' share of the pixels (~15 % at 128 px):
    balanced against it, the perceptual term started ~7x smaller than the step's L1 (the full-mode
    perceptual ablation before this fix), not as large as it.
    """
    with torch.no_grad():
        model.eval()
        K = sample.num_cameras
        H, W = sample.images.shape[1:3]
        batch, query = _rays(model, sample, device)
        pred_rays = model(*sample.normal_maps(device), query)  # (N, 3)
        target, target_rays = _targets(sample, batch, device)  # (K, H, W, 3), (N, 3)
        terms = step_loss(pred_rays, target_rays, perceptual=perceptual, weight=1.0,
                          pred_images=paint_images(pred_rays, batch, K, H, W), target_images=target,
                          masks=torch.from_numpy(sample.masks).to(device), generator=torch.Generator().manual_seed(0))
        return float(terms.l1 / terms.perceptual.clamp_min(1e-12))
