"""Per-frame SMPL fitting: one shared shape and per-frame translation + pose to target vertices or joints.

The objective, over all frames at once (batched), in the template's model units (metres for SMPL):

    E = mean_f,p w_p |x_fp(theta_f, t_f, beta) - y_fp|^2 / FIT_UNIT^2
        + pose_prior_weight  * mean_f |theta_f[3:]|^2      (the 69 body-joint axis-angle values)
        + betas_prior_weight * |beta|^2

with ``x`` the posed vertices (and/or joints) of :class:`~deliffas.geometry.templates.smpl.SMPLTemplate`,
``FIT_UNIT`` = 1 cm (so the data term reads in cm^2), and the two priors a zero-mean Gaussian on the
body pose and on the betas (the global orientation and translation are free). Initialisation: per
frame, the rigid (Kabsch) alignment of the mean-shape rest template to the targets gives the global
orientation and translation; with target vertices, each joint's rotation then starts from the rigid
alignment of the vertices it dominates (in tree order; joints dominating fewer than
``MIN_PART_VERTS`` vertices inherit their parent's rotation); betas start at zero. Then (optionally)
Adam, then L-BFGS (strong Wolfe line search) on all unknowns. Everything runs on the targets'
device and dtype.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import torch
from jaxtyping import Float
from torch import Tensor

from deliffas.checks import check_finite, check_shape
from deliffas.io.body_models.smpl import NUM_JOINTS
from deliffas.geometry.templates.smpl import SMPLTemplate

__all__ = ["SMPLFitConfig", "SMPLFitResult", "fit_smpl", "FIT_UNIT_M"]

log = logging.getLogger(__name__)

FIT_UNIT_M = 0.01
"""Length unit of the data term (1 cm): E's data term is a mean squared distance in cm^2."""
MIN_PART_VERTS = 8
"""Vertices a joint must dominate (largest skinning weight) to get its own starting rotation."""


@dataclass(frozen=True)
class SMPLFitConfig:
    """How :func:`fit_smpl` optimises."""

    adam_steps: int = 100
    """Adam iterations before L-BFGS (0 skips Adam). Measured on 8 frames of the procedural body
    (docs/geometry.md): L-BFGS alone 1.0 mm, with 100 Adam steps first 0.65 mm, +20 % time."""
    adam_lr: float = 0.01
    """Adam learning rate (radians / model units per step, roughly)."""
    lbfgs_rounds: int = 20
    """L-BFGS rounds (0 skips L-BFGS); the progress bar advances once per round."""
    lbfgs_iters: int = 20
    """L-BFGS iterations per round, each with a strong-Wolfe line search (history kept across rounds)."""
    pose_prior_weight: float = 1e-3
    """Weight of mean_f |body pose_f|^2 (radians^2), against the data term in cm^2."""
    betas_prior_weight: float = 1e-3
    """Weight of |betas|^2."""
    joint_weight: float = 1.0
    """Weight of the joint term when both vertices and joints are given (vertices weigh 1)."""
    fit_betas: bool = True
    """Optimise the shared betas; False keeps ``init_betas`` (zeros by default)."""
    progress: bool = False
    """Show a tqdm progress bar."""


@dataclass(frozen=True)
class SMPLFitResult:
    """The fitted parameters and how well they fit.

    Attributes:
        params: (N, 3 + 72 + NB) ``SMPLTemplate`` rows [transl (model units), pose, betas], the
            targets' dtype and device, detached.
        betas: (NB,) the shared shape coefficients (also in every row of ``params``).
        residual_mm: (N,) per frame, mean Euclidean distance between the fitted and the target
            vertices (joints when only joints were given), world units: mm at the default scale 1000.
        loss: final value of the objective E (module docstring).
    """

    params: Float[Tensor, "N P"]
    betas: Float[Tensor, "NB"]
    residual_mm: Float[Tensor, "N"]
    loss: float


def _kabsch(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotations R minimising |R (src - mean) - (dst - mean)|^2; src (P, 3), dst (N, P, 3)."""
    a = src - src.mean(0)
    b = dst - dst.mean(1, keepdim=True)
    H = torch.einsum("pi,npj->nij", a, b)  # (N, 3, 3)
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vh.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=1))
    return Vh.transpose(1, 2) @ D @ U.transpose(1, 2)


def _rotvec(R: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotation matrices -> (N, 3) axis-angle (scipy, robust at 180 degrees; init only)."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(R.detach().cpu().double().numpy()).as_rotvec()
    return torch.as_tensor(rv, dtype=R.dtype, device=R.device)


def _initial_rigid(template: SMPLTemplate, target_verts: torch.Tensor | None,
                   target_joints: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame global orientation (N, 3) and translation (N, 3, model units) from a rigid alignment."""
    dtype = (target_verts if target_verts is not None else target_joints).dtype
    rest_v = template.v_template.to(dtype)
    rest_j = template.J_regressor.to(dtype) @ rest_v  # (24, 3) world units
    src, dst = (rest_v, target_verts) if target_verts is not None else (rest_j, target_joints)
    R = _kabsch(src, dst)
    # posed = R (rest - J0) + J0 + transl; matching centroids gives transl
    c_src, c_dst, j0 = src.mean(0), dst.mean(1), rest_j[0]
    transl = c_dst - torch.einsum("nij,j->ni", R, c_src - j0) - j0
    return _rotvec(R), transl / template.scale


def _initial_pose_from_parts(template: SMPLTemplate, target_verts: torch.Tensor) -> torch.Tensor:
    """(N, 72) starting pose: per joint in tree order, the rigid alignment of the vertices it dominates."""
    weights = template.lbs_weights.to(target_verts.dtype)
    rest = template.v_template.to(target_verts.dtype)
    dominant = weights.argmax(1)
    parents = template.parents.tolist()
    glob: list[torch.Tensor] = []
    pose = torch.zeros(target_verts.shape[0], 3 * NUM_JOINTS, dtype=target_verts.dtype, device=target_verts.device)
    for j in range(NUM_JOINTS):
        idx = torch.nonzero(dominant == j)[:, 0]
        if j == 0 and len(idx) < MIN_PART_VERTS:  # the root falls back to the whole body
            idx = torch.arange(len(rest), device=rest.device)
        if len(idx) >= MIN_PART_VERTS:
            glob.append(_kabsch(rest[idx], target_verts[:, idx]))
        else:
            glob.append(glob[parents[j]])
        local = glob[j] if j == 0 else glob[parents[j]].transpose(1, 2) @ glob[j]
        pose[:, 3 * j:3 * j + 3] = _rotvec(local)
    return pose


def _minimise(objective: Callable[[], torch.Tensor], unknowns: list[torch.Tensor], config: SMPLFitConfig) -> None:
    """``config.adam_steps`` of Adam, then ``config.lbfgs_rounds`` of L-BFGS on ``objective`` over ``unknowns``."""
    from tqdm.auto import tqdm  # tqdm is a dependency; imported here so importing geometry stays light

    bar = tqdm(total=config.adam_steps + config.lbfgs_rounds, desc="fit_smpl", disable=not config.progress)
    if config.adam_steps:
        adam = torch.optim.Adam(unknowns, lr=config.adam_lr)
        for _ in range(config.adam_steps):
            adam.zero_grad(set_to_none=True)
            loss = objective()
            loss.backward()
            adam.step()
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item():.4g}", refresh=False)
    if config.lbfgs_rounds:
        lbfgs = torch.optim.LBFGS(unknowns, lr=1.0, max_iter=config.lbfgs_iters, history_size=20,
                                  line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-12, tolerance_change=1e-15)

        def closure() -> torch.Tensor:
            lbfgs.zero_grad(set_to_none=True)
            value = objective()
            value.backward()
            return value

        for _ in range(config.lbfgs_rounds):
            loss = lbfgs.step(closure)
            bar.update(1)
            bar.set_postfix(loss=f"{float(loss.detach()):.4g}", refresh=False)
    bar.close()


def fit_smpl(template: SMPLTemplate, target_verts: torch.Tensor | None = None,
             target_joints: torch.Tensor | None = None, config: SMPLFitConfig = SMPLFitConfig(),
             init_betas: torch.Tensor | None = None) -> SMPLFitResult:
    """Fit one shape and per-frame translation + pose of ``template`` to N frames of targets.

    Args:
        template: the SMPL template (its buffers on the targets' device and dtype).
        target_verts: (N, V, 3) posed vertices in the template's vertex order, world units (mm at
            scale 1000), or None.
        target_joints: (N, 24, 3) SMPL joints (the template's regressed joints), world units, or None.
        config: optimiser settings and prior weights.
        init_betas: (NB,) starting betas (zeros when None).

    Returns:
        SMPLFitResult with params (N, 3 + 72 + NB), betas (NB,), residual_mm (N,) and the final loss.

    Raises:
        ValueError: no targets, wrong shapes, non-finite values, or a template on another
            device/dtype than the targets.
    """
    if target_verts is None and target_joints is None:
        raise ValueError("fit_smpl: give target_verts (N, V, 3) and/or target_joints (N, 24, 3)")
    sizes: dict[str, int] = {}
    if target_verts is not None:
        sizes = check_shape("target_verts", target_verts, "N V 3", {"V": template.num_verts})
        check_finite("target_verts", target_verts)
    if target_joints is not None:
        sizes = check_shape("target_joints", target_joints, "N J 3", {**sizes, "J": NUM_JOINTS})
        check_finite("target_joints", target_joints)
    ref = target_verts if target_verts is not None else target_joints
    if template.v_template.device != ref.device or template.v_template.dtype != ref.dtype:
        raise ValueError(f"fit_smpl: the template is {template.v_template.dtype} on {template.v_template.device} "
                         f"but the targets are {ref.dtype} on {ref.device}; move the template with .to()")
    N, NB = sizes["N"], template.num_betas
    factory = dict(dtype=ref.dtype, device=ref.device)
    with torch.no_grad():
        root, transl0 = _initial_rigid(template, target_verts, target_joints)
        pose = torch.zeros(N, 3 * NUM_JOINTS, **factory)
        pose[:, :3] = root
        if target_verts is not None:
            pose = _initial_pose_from_parts(template, target_verts)
            start = torch.cat([transl0, pose, torch.zeros(N, NB, **factory)], dim=1)
            transl0 = transl0 + (target_verts.mean(1) - template.pose(start).mean(1)) / template.scale
    pose.requires_grad_(True)
    transl = transl0.clone().requires_grad_(True)
    betas = (torch.zeros(1, NB, **factory) if init_betas is None
             else init_betas.detach().to(**factory).reshape(1, NB).clone())
    betas.requires_grad_(config.fit_betas)
    unknowns = [pose, transl] + ([betas] if config.fit_betas else [])
    inv_unit2 = 1.0 / (FIT_UNIT_M * FIT_UNIT_M * template.scale * template.scale)  # world units^2 -> cm^2

    def params() -> torch.Tensor:
        return torch.cat([transl, pose, betas.expand(N, NB)], dim=1)

    def objective() -> torch.Tensor:
        verts, joints = template.pose_with_joints(params())
        data = 0.0
        if target_verts is not None:
            data = ((verts - target_verts) ** 2).sum(-1).mean() * inv_unit2
        if target_joints is not None:
            w = config.joint_weight if target_verts is not None else 1.0
            data = data + w * ((joints - target_joints) ** 2).sum(-1).mean() * inv_unit2
        prior = config.pose_prior_weight * (pose[:, 3:] ** 2).sum(1).mean()
        return data + prior + config.betas_prior_weight * (betas ** 2).sum()

    _minimise(objective, unknowns, config)
    with torch.no_grad():
        final = objective()
        verts, joints = template.pose_with_joints(params())
        if target_verts is not None:
            residual = (verts - target_verts).norm(dim=-1).mean(1)
        else:
            residual = (joints - target_joints).norm(dim=-1).mean(1)
    log.info("fit_smpl: %d frames, loss %.4g, mean residual %.3f (max frame %.3f) world units", N, float(final),
             float(residual.mean()), float(residual.max()))
    return SMPLFitResult(params().detach(), betas.detach()[0], residual, float(final))
