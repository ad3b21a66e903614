"""How ``fit_body`` fits the body model to keypoints and masks (:class:`BodyFitConfig`); light, so the CLI reads it
without torch."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.options import check_fields, non_negative_float, non_negative_int, opt, positive_float, positive_int

__all__ = ["BodyFitConfig"]


@dataclass(frozen=True)
class BodyFitConfig:
    """How :func:`deliffas.geometry.body_fit.fit_body` optimises.

    Lengths in the losses are in cm (so a weight of 1 on a squared distance reads "1 per cm^2"), angles in radians.
    """

    iters_keypoints: int = opt(300, help="Adam steps of the keypoint stage (all frames batched; 0 keeps the "
                               "closed-form start)",
                               parse=non_negative_int)
    iters_silhouette: int = opt(150, help="Adam steps of the silhouette stage (with cameras and masks; 0 skips it)",
                                 parse=non_negative_int)
    lr: float = opt(0.02, help="peak Adam step of the pose, rad (betas 10x, translations 0.5x m; "
                            "silhouette stage at half; cosine decay to 1/10)", parse=positive_float)
    warmup: float = opt(0.2, help="fraction of the keypoint steps that move only the root and translation",
                        parse=non_negative_float)
    robust_mm: float = opt(50.0, help="Geman-McClure scale of the keypoint distances, mm (residuals well "
                       "beyond it stop pulling)", parse=positive_float)
    pose_prior: float = opt(0.05, help="weight of |body pose|^2 (69 values, rad^2; not the root) per frame",
                            parse=non_negative_float)
    hinge_prior: float = opt(1.0, help="weight of knee/elbow rotation off their hinge axis and bending backwards",
                             parse=non_negative_float)
    shape_prior: float = opt(0.1, help="weight of |betas|^2", parse=non_negative_float)
    smooth: float = opt(0.1, help="weight of squared second differences over consecutive frames of the "
                        "posed joints (cm) and body pose (rad)",
                        parse=non_negative_float)
    silhouette: float = opt(16.0, help="weight of the silhouette terms, cover + outside * outside-term "
                            "(robust mean squared distances, cm^2)", parse=non_negative_float)
    outside: float = opt(1.0, help="weight of the vertices-outside-the-mask term (the mask-coverage term weighs 1)",
                         parse=non_negative_float)
    outside_margin_mm: float = opt(10.0, help="how far a vertex may lie outside the mask for free, mm",
                                   parse=non_negative_float)
    silhouette_robust_mm: float = opt(80.0, help="Geman-McClure scale of the silhouette distances, mm",
                                      parse=positive_float)
    keypoints_in_silhouette: float = opt(0.3, help="weight of the keypoint term in the silhouette stage",
                                         parse=non_negative_float)
    offsets: bool = opt(True, help="fit per-vertex offsets along the rest normals, shared by all frames (SMPL+D), "
                        "in the silhouette stage")
    offset_smooth: float = opt(3.0, help="weight of the squared differences of neighbouring offsets (cm^2)",
                               parse=non_negative_float)
    offset_prior: float = opt(1.0, help="weight of the squared offsets (cm^2)", parse=non_negative_float)
    mask_height: int = opt(256, help="height the masks are downsampled to (never up) for the silhouette "
                           "terms and the IoU",
                           parse=positive_int)
    mask_samples: int = opt(1024, help="mask pixels drawn per view and frame for the coverage term (each "
                            "the body does not cover pulls its nearest projected vertex)",
                            parse=positive_int)
    reassign_every: int = opt(5, help="silhouette steps between searches of each sample's nearest "
                            "projected vertices", parse=positive_int)
    seed: int = opt(0, help="seed of the mask samples")

    def __post_init__(self) -> None:
        check_fields(self)  # each option's own check, as on the command line
