"""How ``fit_body`` fits the body model to keypoints and masks (:class:`BodyFitConfig`); light, so the CLI reads it
without torch."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.options import non_negative_float, non_negative_int, opt, positive_float, positive_int

__all__ = ["BodyFitConfig"]


@dataclass(frozen=True)
class BodyFitConfig:
    """How :func:`deliffas.geometry.body_fit.fit_body` optimises.

    Lengths in the losses are in cm (so a weight of 1 on a squared distance reads "1 per cm^2"), angles in radians.
    """

    iters_keypoints: int = opt(300, help="Adam steps of the keypoint stage (all frames batched)",
                               parse=non_negative_int)
    """Adam steps of the keypoint stage (all frames at once; 0 keeps the closed-form initialisation)."""
    iters_silhouette: int = opt(150, help="Adam steps of the silhouette stage", parse=non_negative_int)
    """Adam steps of the silhouette stage (run only when cameras and masks are given; 0 skips it)."""
    lr: float = opt(0.02, help="peak Adam learning rate of the pose, radians per step", parse=positive_float)
    """Peak Adam step of the pose (rad; betas 10x, translations 0.5x m); silhouette stage at half; cosine to 1/10."""
    warmup: float = opt(0.2, help="fraction of the keypoint steps that move only the root and translation",
                        parse=non_negative_float)
    """Fraction of ``iters_keypoints`` moving only the root orientation and translation (body pose and betas fixed)."""
    robust_mm: float = opt(50.0, help="Geman-McClure scale of the keypoint distances, mm", parse=positive_float)
    """Geman-McClure scale of the keypoint term: residuals well beyond it stop pulling (a mis-triangulated joint)."""
    pose_prior: float = opt(0.05, help="weight of the L2 prior on the body pose (not the root)",
                            parse=non_negative_float)
    """Weight of sum |body pose|^2 (69 axis-angle values, radians^2) per frame, against the keypoint term in cm^2."""
    hinge_prior: float = opt(1.0, help="weight of the knee/elbow hinge prior", parse=non_negative_float)
    """Weight of the knees' and elbows' rotations off their hinge axis and of their bending backwards (radians^2)."""
    shape_prior: float = opt(0.005, help="weight of the L2 prior on the betas", parse=non_negative_float)
    """Weight of |betas|^2."""
    smooth: float = opt(0.1, help="weight of second differences over time of the joints and pose",
                        parse=non_negative_float)
    """Weight of the squared second differences over consecutive frames of the posed joints (cm) and body pose (rad)."""
    silhouette: float = opt(4.0, help="weight of the silhouette terms", parse=non_negative_float)
    """Weight of the silhouette terms, ``cover + outside * outside-term`` (robust mean squared distances, cm^2)."""
    outside: float = opt(0.3, help="weight of the vertices-outside-the-mask term (the mask-coverage term weighs 1)",
                         parse=non_negative_float)
    """Relative weight of the term pulling vertices into the mask; below 1 so the body covers the mask."""
    outside_margin_mm: float = opt(10.0, help="how far a vertex may lie outside the mask for free, mm",
                                   parse=non_negative_float)
    """Distance outside the mask a vertex may lie at no cost (the template may exceed the mask a little)."""
    silhouette_robust_mm: float = opt(80.0, help="Geman-McClure scale of the silhouette distances, mm",
                                      parse=positive_float)
    """Geman-McClure scale of both silhouette terms: mask errors far from the body stop pulling."""
    keypoints_in_silhouette: float = opt(0.3, help="weight of the keypoint term in the silhouette stage",
                                         parse=non_negative_float)
    """Weight of the keypoint term during the silhouette stage (1 in the keypoint stage)."""
    mask_height: int = opt(256, help="masks are downsampled to this height for the silhouette terms",
                           parse=positive_int)
    """Height in pixels of the masks the silhouette terms and ``silhouette_iou`` use (never upsampled)."""
    mask_samples: int = opt(256, help="mask pixels sampled per view and frame for the coverage term",
                            parse=positive_int)
    """Pixels drawn once inside each mask; each the body does not cover pulls its nearest projected vertex."""
    reassign_every: int = opt(5, help="silhouette steps between nearest-vertex searches", parse=positive_int)
    """Steps between searches of each mask sample's 8 nearest projected vertices and of whether the body covers it."""
    seed: int = opt(0, help="seed of the mask samples")
    """Seed of the random mask samples (the fit is deterministic for a given seed)."""
