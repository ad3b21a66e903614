"""Fitting SMPL to surfaces of another topology, frame by frame (e.g. a DDC capture's posed template).

With no vertex correspondence, the data term is the symmetric closest-point distance between the
posed SMPL vertices and the target points (robust: sqrt(d^2 + 1 mm^2), both directions, nearest
neighbours re-found every iteration with a k-d tree). The first frame fits translation, global
orientation and the shared betas first (``stage_a`` of its iterations), then the body pose too;
every later frame starts from the previous frame's parameters (the betas stay those of the first
frame) and runs ``frame_iters`` Adam steps. Priors: a zero-mean Gaussian on the 69 body-pose values
and on the betas. For targets with SMPL's own topology use :func:`deliffas.geometry.smpl_fit.fit_smpl`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from deliffas.geometry.smpl_surface_fit_config import SurfaceFitConfig
from deliffas.geometry.templates.smpl import SMPLTemplate

__all__ = ["SurfaceFitConfig", "SurfaceFitResult", "fit_smpl_to_surfaces"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SurfaceFitResult:
    """Fitted ``SMPLTemplate`` rows and how far the surfaces stay apart.

    Attributes:
        params: (N, 3 + 72 + NB) float64 rows [transl (model units), pose, betas]; one betas for all.
        residual_mm: (N,) mean symmetric closest-point distance per frame, world units (mm).
    """

    params: Float[np.ndarray, "N P"]
    residual_mm: Float[np.ndarray, "N"]


def _distances(tree_target: cKDTree, target: np.ndarray, verts: np.ndarray) -> np.ndarray:
    return np.concatenate([tree_target.query(verts)[0], cKDTree(verts).query(target)[0]])


def _fit_frame(smpl: SMPLTemplate, target: np.ndarray, start: torch.Tensor, iters: int, stage_a: int,
               fit_betas: bool, config: SurfaceFitConfig) -> tuple[torch.Tensor, float]:
    """Adam on one frame from ``start`` (D,); returns the best parameters seen and their mean distance (mm)."""
    dtype = smpl.v_template.dtype
    tree = cKDTree(target)
    target_t = torch.as_tensor(target, dtype=dtype)
    nb = smpl.num_betas
    transl = start[:3].clone().requires_grad_(True)
    orient = start[3:6].clone().requires_grad_(True)
    body = start[6:75].clone().requires_grad_(True)
    betas = start[75:75 + nb].clone().requires_grad_(fit_betas)
    groups = [{"params": [transl], "lr": 5e-3}, {"params": [orient, body], "lr": 1e-2}]
    if fit_betas:
        groups.append({"params": [betas], "lr": 5e-2})
    opt = torch.optim.Adam(groups)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda it: 1.0 - 0.9 * it / max(iters, 1))
    best = (float("inf"), start.clone())
    for it in range(iters + 1):
        params = torch.cat([transl, orient, body if it >= stage_a else body.detach(), betas])
        verts = smpl.pose(params[None])[0]  # (V, 3) mm
        v_np = verts.detach().double().numpy()
        d_st, nn_t = tree.query(v_np)  # SMPL -> target
        d_ts, nn_s = cKDTree(v_np).query(target)  # target -> SMPL
        mean = float(np.concatenate([d_st, d_ts]).mean())
        if mean < best[0]:  # Adam's normalised steps can leave a good solution: keep the best
            best = (mean, params.detach().clone())
        if it == iters:
            break
        data = (torch.sqrt(((verts - target_t[nn_t]) ** 2).sum(-1) + 1.0).mean()
                + torch.sqrt(((target_t - verts[nn_s]) ** 2).sum(-1) + 1.0).mean())
        loss = data + config.pose_prior * 100.0 * (body ** 2).sum() + config.beta_prior * 100.0 * (betas ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return best[1], best[0]


def fit_smpl_to_surfaces(smpl: SMPLTemplate, targets: list[np.ndarray] | np.ndarray,
                         config: SurfaceFitConfig = SurfaceFitConfig()) -> SurfaceFitResult:
    """Fit one shape and per-frame pose + translation of ``smpl`` to a sequence of surfaces.

    Args:
        smpl: the template (world units mm at its default scale).
        targets: N arrays (P_f, 3) of surface points per frame, world mm, in temporal order.

    Returns:
        the fitted rows and per-frame residuals (see :class:`SurfaceFitResult`).
    """
    frames = [np.asarray(t, np.float64) for t in targets]
    if not frames:
        raise ValueError("fit_smpl_to_surfaces: no target frames")
    for i, t in enumerate(frames):
        if t.ndim != 2 or t.shape[1] != 3 or len(t) < 10 or not np.isfinite(t).all():
            raise ValueError(f"fit_smpl_to_surfaces: target {i} must be (P >= 10, 3) finite points, got {t.shape}")
    frames = [t[:: max(1, len(t) // config.max_points)] for t in frames]
    with torch.no_grad():
        rest = smpl.pose(smpl.rest_params()).double().numpy()[0]
    start = smpl.rest_params()[0].clone()
    start[:3] = torch.as_tensor((frames[0].mean(0) - rest.mean(0)) / smpl.scale)
    out, residual = [], []
    bar = tqdm(frames, desc="fit smpl", unit="frame", disable=not config.progress)
    for i, target in enumerate(bar):
        first = i == 0
        params, res = _fit_frame(smpl, target, start, config.first_iters if first else config.frame_iters,
                                 int(config.stage_a * config.first_iters) if first else 0, first, config)
        out.append(params)
        residual.append(res)
        start = params
        bar.set_postfix(residual_mm=f"{res:.1f}")
    log.info("fit_smpl_to_surfaces: %d frames, mean residual %.2f mm (max %.2f)", len(out), float(np.mean(residual)),
             float(np.max(residual)))
    return SurfaceFitResult(torch.stack(out).double().numpy(), np.asarray(residual))
