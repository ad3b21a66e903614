"""How ``fit_smpl_to_surfaces`` optimises (:class:`SurfaceFitConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.options import opt, positive_int

__all__ = ["SurfaceFitConfig"]


@dataclass(frozen=True)
class SurfaceFitConfig:
    """How :func:`deliffas.geometry.smpl_surface_fit.fit_smpl_to_surfaces` optimises."""

    first_iters: int = opt(300, help="Adam steps on the first frame (shape, global pose, then body pose)", parse=positive_int)
    stage_a: float = 0.4
    """Fraction of ``first_iters`` that move translation, global orientation and betas only."""
    frame_iters: int = opt(40, help="Adam steps per later frame, from the previous frame's parameters", parse=positive_int)
    pose_prior: float = 1e-2
    """Weight of |body pose|^2 (rad^2) x 100, against the data term in mm."""
    beta_prior: float = 1e-3
    """Weight of |betas|^2 x 100."""
    max_points: int = 3000
    """Target points used per frame (an even subsample of larger surfaces)."""
    progress: bool = False
    """Show a tqdm progress bar over frames."""
