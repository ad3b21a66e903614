"""Fit the SMPL-layout body to triangulated 3-D keypoints and person masks (the body fit of ``deliffas ingest``).

Unknowns: one shape (betas) shared by every frame and, per frame, the root orientation, the 69 body-pose values
and the translation of :class:`~deliffas.geometry.templates.smpl.SMPLTemplate` rows ``[transl (model units),
axis-angle pose (72), betas]``. The world is the calibration's: mm, any up axis (a mocap lab's z-up included).

1. **Initialisation** (closed form, numpy; :func:`initial_body_params`): per frame, the confidence-weighted
   Kabsch rotation of the rest torso joints (hips, shoulders) onto their keypoints gives the root orientation and
   translation (at least 3 of the 4 needed); each limb joint (hips, knees, ankles, shoulders, elbows) starts at
   the smallest rotation turning its rest bone towards its bone's keypoints. Frames (or bones) without those
   keypoints take the nearest frame's values; the root is then smoothed over +-2 frames.
2. **Keypoint stage** (``iters_keypoints`` Adam steps, all frames batched; only the 24 joints and the landmarks
   are posed, so a step is cheap): a confidence-weighted Geman-McClure distance (``robust_mm``) of the body's
   ``landmarks`` (:mod:`deliffas.geometry.body_landmarks`: joints, or surface points such as the ears and toe tips)
   to the keypoints, an L2 prior on the body pose (``pose_prior``) with a hinge prior on knees and elbows
   (``hinge_prior``: rotation off their bending axis, bending backwards), an L2 prior on the betas
   (``shape_prior``) and squared second differences over consecutive frames of the posed joints and body pose
   (``smooth``). The first ``warmup`` of the steps move only root and translation.
3. **Silhouette stage** (``iters_silhouette`` steps, with cameras and masks;
   :mod:`deliffas.geometry.body_fit_silhouette`): the posed vertices projected into every view, an *outside* term
   (vertices beyond ``outside_margin_mm`` outside the mask, weight ``outside``) and a *cover* term (sampled mask
   pixels outside the body's projected triangles pull their nearest projected vertex, weight 1), both times
   ``silhouette``, with the keypoint term kept at ``keypoints_in_silhouette`` so the pose stays anatomical. The
   cover term weighs more: the body should cover the mask (DELIFFAS's outer shell lies a few cm outside the
   template), never be thinner. With ``offsets`` the stage also moves each rest vertex along its normal, one
   offset per vertex shared by all frames (:mod:`deliffas.geometry.body_fit_offsets`, priors ``offset_smooth``
   and ``offset_prior``): clothing and hair the shape space cannot follow.
4. **Result**: per keypoint the distance of its fitted joint, per view the IoU of the fitted body's filled
   silhouette and the mask at ``mask_height``.

Lengths in the losses are cm, angles radians; the tensors are on the template's device in its dtype.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
from jaxtyping import Bool, Float, Float64, Integer, Real, UInt8
from scipy.spatial.transform import Rotation
from torch import Tensor

from deliffas.checks import check_shape
from deliffas.io.body_models.smpl import NUM_JOINTS
from deliffas.io.cameras import Camera
from deliffas.geometry.body_fit_config import BodyFitConfig
from deliffas.geometry.body_fit_offsets import OFFSETS_LR, RestOffsets
from deliffas.geometry.body_landmarks import BodyLandmarks, body_landmarks, pose_landmarks
from deliffas.geometry.smpl_body import SMPL_JOINT_NAMES
from deliffas.geometry import body_fit_silhouette as sil
from deliffas.geometry.smpl import batch_rigid_transform, batch_rodrigues
from deliffas.geometry.templates.smpl import SMPLTemplate

__all__ = ["BodyFitConfig", "BodyFitResult", "fit_body", "initial_body_params", "TORSO_JOINTS", "LIMB_BONES"]

TORSO_JOINTS = (1, 2, 16, 17)
"""SMPL joints whose keypoints give a frame's root orientation: l_hip, r_hip, l_shoulder, r_shoulder."""
LIMB_BONES = ((1, 4), (2, 5), (4, 7), (5, 8), (7, 10), (8, 11), (16, 18), (17, 19), (18, 20), (19, 21))
"""(joint, child) pairs: the initial rotation of ``joint`` turns its rest bone towards the child's keypoint."""
_HINGES = ((4, 0, 1.0), (5, 0, 1.0), (18, 1, -1.0), (19, 1, 1.0))
"""(joint, bending axis, sign of bending): knees bend about +x; the elbows about y (left -, right +) in the rest
frame (y up, facing +z, left at +x)."""
BETAS_LR = 10.0
"""Adam's learning rate of the betas, in units of ``config.lr`` (one unit of beta moves the surface 1-4 cm)."""
TRANSL_LR = 0.5
"""Adam's learning rate of the translations (model units: metres), in units of ``config.lr``."""
_SMOOTH_WINDOW = (1.0, 2.0, 3.0, 2.0, 1.0)
"""Weights of the moving average smoothing the initial root over +-2 frames."""
_INIT_OUTLIER_MM = 150.0
"""A torso keypoint further than this from its rigidly aligned rest joint is left out of the initial root."""


@dataclass(frozen=True)
class BodyFitResult:
    """The fitted rows and how well they fit.

    Attributes:
        params: (N, D) float64 ``SMPLTemplate`` rows [transl (model units), pose (72), betas]; the betas are the
            same on every row.
        joint_error_mm: (N, J) float64 distance of each fitted landmark to its keypoint, mm; NaN where the keypoint
            is invalid.
        silhouette_iou: (N, C) float64 IoU of the fitted body's silhouette and the mask at ``mask_height``; NaN where
            the mask is empty; None without cameras and masks.
        losses: the final value of each term (unweighted; ``total`` is the last stage's weighted sum).
        rest_offsets_mm: (V, 3) float64 per-vertex offsets of the rest shape, mm (zeros without
            ``config.offsets`` or masks); the fitted body is the template with them added to ``v_template``
            (:func:`~deliffas.geometry.body_fit_offsets.with_rest_offsets`).
    """

    params: Float64[np.ndarray, "N D"]
    joint_error_mm: Float64[np.ndarray, "N J"]
    silhouette_iou: Float64[np.ndarray, "N C"] | None
    losses: dict[str, float]
    rest_offsets_mm: Float64[np.ndarray, "V 3"]


# --------------------------------------------------------------------------------------------- initialisation
def _clean(keypoints: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, J, 3) float64 points (0 where invalid) and (N, J) weights in [0, 1] (0 where invalid)."""
    kp = np.asarray(keypoints, np.float64)
    w = np.nan_to_num(np.clip(np.asarray(conf, np.float64), 0.0, 1.0), nan=0.0)
    w = np.where(np.isfinite(kp).all(axis=2), w, 0.0)
    return np.where(w[..., None] > 0, np.nan_to_num(kp), 0.0), w


def _kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted rotations (N, 3, 3) taking src (N, P, 3) to dst (N, P, 3), and both weighted centroids (N, 3)."""
    sw = np.maximum(w.sum(1, keepdims=True), 1e-12)
    cs, cd = (w[..., None] * src).sum(1) / sw, (w[..., None] * dst).sum(1) / sw
    H = np.einsum("np,npi,npj->nij", w, src - cs[:, None], dst - cd[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    D = np.zeros((len(w), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    return np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2), cs, cd


def _per_joint(kp: np.ndarray, w: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 24, 3) keypoint of each SMPL joint (the most confident of its columns) and (N, 24) bool valid."""
    N = len(kp)
    points, best = np.zeros((N, NUM_JOINTS, 3)), np.zeros((N, NUM_JOINTS))
    for j, jid in enumerate(ids):  # J columns
        better = w[:, j] > best[:, jid]
        points[better, jid], best[better, jid] = kp[better, j], w[better, j]
    return points, best > 0


def _fill_nearest(values: np.ndarray, ok: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``values`` (N, ...) with every row where ``ok`` is False replaced by the nearest (in time) ok row."""
    if ok.all() or not ok.any():
        return values
    good = np.flatnonzero(ok)
    after = np.clip(np.searchsorted(times[good], times), 1, len(good) - 1) if len(good) > 1 else np.zeros_like(times)
    before = np.maximum(after - 1, 0)
    closer = np.abs(times - times[good[before]]) <= np.abs(times[good[after]] - times)
    nearest = good[np.where(closer, before, after)]
    return values[np.where(ok, np.arange(len(ok)), nearest)]


def _smooth_root(R: np.ndarray, t: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Moving averages over +-2 frames (frames at most 2 apart in time): rotations projected back to SO(3)."""
    half = len(_SMOOTH_WINDOW) // 2
    N = len(R)
    R_out, t_out = np.empty_like(R), np.empty_like(t)
    for n in range(N):  # frames
        lo, hi = max(0, n - half), min(N, n + half + 1)
        k = np.arange(lo, hi)
        wk = np.asarray(_SMOOTH_WINDOW)[k - n + half] * (np.abs(times[k] - times[n]) <= half)
        t_out[n] = (wk[:, None] * t[k]).sum(0) / wk.sum()
        U, _, Vt = np.linalg.svd((wk[:, None, None] * R[k]).sum(0))
        R_out[n] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt
    return R_out, t_out


def _distinct(w: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(N,) how many distinct joints of ``ids`` (P,) have a positive weight in ``w`` (N, P) per frame."""
    return np.stack([(w[:, ids == j] > 0).any(1) for j in np.unique(ids)], 1).sum(1)


def _robust_kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray, ids: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_kabsch` of rest joints src (P, 3) onto keypoints dst (N, P, 3), dropping per frame the keypoint
    furthest from its aligned joint while one lies beyond ``_INIT_OUTLIER_MM``; also (N,) bool: the frame kept at
    least 3 distinct joints, all within it."""
    w = w.copy()
    src = np.broadcast_to(src, dst.shape)
    for drops in range(src.shape[1] + 1):  # at most one keypoint dropped per round
        R, cs, cd = _kabsch(src, dst, w)
        resid = np.linalg.norm(np.einsum("nij,npj->npi", R, src - cs[:, None]) + cd[:, None] - dst, axis=2)
        resid[w <= 0] = 0.0
        bad = np.flatnonzero(resid.max(1) > _INIT_OUTLIER_MM)
        if not len(bad) or drops == src.shape[1]:
            break
        w[bad, resid[bad].argmax(1)] = 0.0
    return R, cs, cd, (_distinct(w, ids) >= 3) & (resid.max(1) <= _INIT_OUTLIER_MM)


def _root_init(rest: np.ndarray, kp: np.ndarray, w: np.ndarray, ids: np.ndarray, times: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame the root rotation (N, 3, 3) and the world position of the rest pelvis J0 after it (N, 3) mm."""
    torso = np.isin(ids, TORSO_JOINTS)
    ok = np.zeros(len(kp), bool)
    for cols in (torso, np.ones_like(torso)):  # the torso; without any torso frame, every keypoint
        if cols.any():
            R, cs, cd, ok = _robust_kabsch(rest[ids[cols]], kp[:, cols], w[:, cols], ids[cols])
            if ok.any():
                break
    if not ok.any():  # no frame with 3 consistent keypoints: upright, centred on them
        ok = w.sum(1) > 0
        R = np.tile(np.eye(3), (len(kp), 1, 1))
        cs, cd = _kabsch(np.broadcast_to(rest[ids], kp.shape), kp, w)[1:]
    pelvis = cd - np.einsum("nij,nj->ni", R, cs - rest[0])
    R, pelvis = _fill_nearest(R, ok, times), _fill_nearest(pelvis, ok, times)
    return _smooth_root(R, pelvis, times)


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3) axis-angle of the smallest rotations turning direction a (3,) towards directions b (N, 3)."""
    a = a / np.linalg.norm(a)
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    cross = np.cross(a, b)
    s, c = np.linalg.norm(cross, axis=1), b @ a
    axis = cross / np.maximum(s, 1e-12)[:, None]
    flip = (s < 1e-9) & (c < 0)  # opposite directions: any axis normal to a
    if flip.any():
        normal = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])
        axis[flip] = normal / np.linalg.norm(normal)
    return axis * np.arctan2(s, c)[:, None]


def _limb_init(rest: np.ndarray, parents: list[int], points: np.ndarray, valid: np.ndarray, root: np.ndarray,
               times: np.ndarray) -> np.ndarray:
    """(N, 72) pose: the root, and per limb joint the swing turning its rest bone towards its keypoints."""
    N = len(points)
    pose = np.zeros((N, NUM_JOINTS, 3))
    glob = np.zeros((N, NUM_JOINTS, 3, 3))
    glob[:, 0] = root
    children = dict(LIMB_BONES)
    for j in range(1, NUM_JOINTS):  # parents precede children
        parent_R = glob[:, parents[j]]
        if j in children:
            child = children[j]
            local_dir = np.einsum("nji,nj->ni", parent_R, points[:, child] - points[:, j])  # parent^T d
            ratio = np.linalg.norm(local_dir, axis=1) / np.linalg.norm(rest[child] - rest[j])
            ok = valid[:, j] & valid[:, child] & (ratio > 0.5) & (ratio < 2.0)  # else an outlier
            if ok.any():
                pose[:, j] = _fill_nearest(_swing(rest[child] - rest[j], local_dir), ok, times)
        glob[:, j] = parent_R @ Rotation.from_rotvec(pose[:, j]).as_matrix()
    pose[:, 0] = _continuous_rotvecs(root)
    return pose.reshape(N, 3 * NUM_JOINTS)


def _continuous_rotvecs(R: np.ndarray) -> np.ndarray:
    """(N, 3) axis-angle of rotations (N, 3, 3), each the one of its two forms (angle a or a - 2 pi) nearest the
    previous frame's, so the root does not jump where the angle passes pi."""
    rv = Rotation.from_matrix(R).as_rotvec()
    for n in range(1, len(rv)):  # frames
        angle = np.linalg.norm(rv[n])
        if angle > 1e-6:
            other = rv[n] * (1.0 - 2.0 * math.pi / angle)
            if np.linalg.norm(other - rv[n - 1]) < np.linalg.norm(rv[n] - rv[n - 1]):
                rv[n] = other
    return rv


def _as_landmarks(template: SMPLTemplate, landmarks: BodyLandmarks | Sequence[int] | np.ndarray) -> BodyLandmarks:
    """``landmarks`` as :class:`BodyLandmarks` (SMPL joint indices become joint landmarks)."""
    if isinstance(landmarks, BodyLandmarks):
        return landmarks
    names = [SMPL_JOINT_NAMES[int(j)] for j in np.asarray(list(landmarks), np.int64)]
    return body_landmarks(template.v_template, template.J_regressor, template.lbs_weights, names)


def _rest_joints(template: SMPLTemplate) -> np.ndarray:
    """(24, 3) float64 rest joints of the mean shape, world units (mm)."""
    with torch.no_grad():
        return (template.J_regressor @ template.v_template).double().cpu().numpy()


def initial_body_params(template: SMPLTemplate, keypoints: Real[np.ndarray, "N J 3"],
                        keypoint_conf: Real[np.ndarray, "N J"],
                        landmarks: BodyLandmarks | Sequence[int] | Integer[np.ndarray, "J"],
                        frame_ids: Integer[np.ndarray, "N"] | None = None) -> Float64[np.ndarray, "N D"]:
    """The closed-form start of :func:`fit_body` (module docstring, step 1): rows with the root, the limb joints
    and the translation set, the rest of the pose and the betas zero.

    Args:
        template: the body model.
        keypoints: (N, J, 3) world mm (NaN allowed where invalid).
        keypoint_conf: (N, J) in [0, 1], 0 = invalid.
        landmarks: the J body points the keypoint columns stand for, or (J,) SMPL joints (0..23); only joint
            landmarks enter the initialisation.
        frame_ids: (N,) increasing frame numbers (nearest frames and smoothing follow them); None = 0..N-1.

    Returns:
        (N, D) float64 rows.
    """
    kp, w = _clean(keypoints, keypoint_conf)
    ids = _as_landmarks(template, landmarks).joints
    kp, w, ids = kp[:, ids >= 0], w[:, ids >= 0], ids[ids >= 0]
    times = np.arange(len(kp)) if frame_ids is None else np.asarray(frame_ids, np.int64)
    rest = _rest_joints(template)
    R, pelvis = _root_init(rest, kp, w, ids, times)
    points, valid = _per_joint(kp, w, ids)
    pose = _limb_init(rest, template.parents.tolist(), points, valid, R, times)
    transl = (pelvis - rest[0]) / template.scale
    return np.concatenate([transl, pose, np.zeros((len(kp), template.num_betas))], axis=1)


# --------------------------------------------------------------------------------------------- optimisation
def _geman_mcclure(d2: Tensor, scale: float) -> Tensor:
    """~d2 for small squared distances, saturating at ``scale^2``."""
    return d2 * scale ** 2 / (d2 + scale ** 2)


class _Problem:
    """The unknowns of all frames (root, body pose, translation, shared betas) and the terms both stages share."""

    def __init__(self, template: SMPLTemplate, init: np.ndarray, kp: np.ndarray, w: np.ndarray,
                 landmarks: BodyLandmarks, times: np.ndarray, config: BodyFitConfig):
        ref = template.v_template
        start = torch.as_tensor(init, dtype=ref.dtype, device=ref.device)
        self.template, self.config = template, config
        self.transl = start[:, :3].clone().requires_grad_(True)
        self.root = start[:, 3:6].clone().requires_grad_(True)
        self.body = start[:, 6:3 * NUM_JOINTS + 3].clone().requires_grad_(True)
        self.betas = start[:1, 3 * NUM_JOINTS + 3:].clone().requires_grad_(True)
        self.target = torch.as_tensor(kp, dtype=ref.dtype, device=ref.device)
        self.weight = torch.as_tensor(w, dtype=ref.dtype, device=ref.device)
        self.landmarks = landmarks
        self.num_weight = max(float(w.sum()), 1e-6)
        self.offsets: RestOffsets | None = None  # set by the silhouette stage with config.offsets
        with torch.no_grad():
            self.j_rest = template.J_regressor @ template.v_template  # (24, 3) mm
            self.j_dirs = torch.einsum("jv,vkl->jkl", template.J_regressor, template.shapedirs)  # (24, 3, NB)
            self.l_weights = torch.as_tensor(landmarks.weights, dtype=ref.dtype, device=ref.device)
            lw = self.l_weights
            self.l_rest = lw @ template.v_template  # (J, 3) mm
            self.l_dirs = torch.einsum("jv,vkl->jkl", lw, template.shapedirs)  # (J, 3, NB)
        steps = np.diff(times)
        self.triples = torch.as_tensor(np.flatnonzero((steps[:-1] == 1) & (steps[1:] == 1)), device=ref.device)
        hinge = [(j - 1) * 3 + a for j, a, _ in _HINGES]
        self.hinge_axis = torch.as_tensor(hinge, device=ref.device)
        self.hinge_sign = torch.as_tensor([s for *_, s in _HINGES], dtype=ref.dtype, device=ref.device)
        off = [(j - 1) * 3 + k for j, a, _ in _HINGES for k in range(3) if k != a]
        self.hinge_off = torch.as_tensor(off, device=ref.device)

    def params(self, free: bool = True) -> Tensor:
        """(N, D) rows; with ``free`` False the body pose and betas are held (detached)."""
        body, betas = (self.body, self.betas) if free else (self.body.detach(), self.betas.detach())
        return torch.cat([self.transl, self.root, body, betas.expand(len(self.body), -1)], dim=1)

    def posed(self, params: Tensor) -> tuple[Tensor, Tensor]:
        """(N, 24, 3) posed joints (``SMPLTemplate.pose_with_joints``'s, without posing the vertices) and (N, J, 3)
        posed landmarks, mm."""
        N = len(params)
        betas = params[0, 3 * NUM_JOINTS + 3:]
        rest = self.j_rest + torch.einsum("jkl,l->jk", self.j_dirs, betas)
        l_rest = self.l_rest + torch.einsum("jkl,l->jk", self.l_dirs, betas)
        if self.offsets is not None:
            rest = rest + self.offsets.joint_shift()
            l_rest = l_rest + self.l_weights @ self.offsets.vectors()
        rot = batch_rodrigues(params[:, 3:3 * NUM_JOINTS + 3].reshape(-1, 3)).reshape(N, NUM_JOINTS, 3, 3)
        posed, A = batch_rigid_transform(rot, rest.expand(N, -1, -1), self.template.parents)
        points = pose_landmarks(self.landmarks, l_rest, A)
        shift = params[:, None, :3] * self.template.scale
        return posed + shift, points + shift

    def terms(self, params: Tensor, posed: tuple[Tensor, Tensor] | None = None) -> dict[str, Tensor]:
        """The keypoint, prior and smoothness terms (unweighted; lengths in cm, angles in radians); ``posed`` is
        :meth:`posed` of ``params`` when already computed."""
        joints, points = self.posed(params) if posed is None else posed
        d2 = ((points - self.target) ** 2).sum(-1) / 100.0
        body = params[:, 6:3 * NUM_JOINTS + 3]
        hinge = ((body[:, self.hinge_off] ** 2).sum(1)
                 + (torch.relu(-self.hinge_sign * body[:, self.hinge_axis]) ** 2).sum(1))
        out = {"keypoints": (self.weight * _geman_mcclure(d2, self.config.robust_mm / 10.0)).sum() / self.num_weight,
               "pose_prior": (body ** 2).sum(1).mean(), "hinge_prior": hinge.mean(),
               "shape_prior": (params[0, 3 * NUM_JOINTS + 3:] ** 2).sum(), "smooth": joints.new_zeros(())}
        if len(self.triples):
            i = self.triples
            acc_j = (joints[i] - 2 * joints[i + 1] + joints[i + 2]) / 10.0
            acc_p = body[i] - 2 * body[i + 1] + body[i + 2]
            out["smooth"] = (acc_j ** 2).sum(-1).mean(-1).mean() + (acc_p ** 2).sum(-1).mean()
        return out

    def vertices(self, params: Tensor) -> Tensor:
        """(N, V, 3) posed vertices of ``params``, mm (with the offsets once the silhouette stage fits them)."""
        return self.template.pose(params) if self.offsets is None else self.offsets.pose(params)

    def weighted(self, terms: dict[str, Tensor], keypoints: float) -> Tensor:
        """The objective: the terms times their weights (``keypoints`` for the keypoint term)."""
        c = self.config
        return (keypoints * terms["keypoints"] + c.pose_prior * terms["pose_prior"]
                + c.hinge_prior * terms["hinge_prior"] + c.shape_prior * terms["shape_prior"]
                + c.smooth * terms["smooth"] + c.silhouette * (terms.get("cover", 0.0)
                                                            + c.outside * terms.get("outside", 0.0))
                + c.offset_smooth * terms.get("offset_smooth", 0.0) + c.offset_prior * terms.get("offset_prior", 0.0))

    def keypoint_step(self, it: int, free: bool) -> Tensor:
        """The keypoint stage's objective at step ``it``."""
        return self.weighted(self.terms(self.params(free)), 1.0)


class _SilhouetteStage:
    """The silhouette stage's objective: keypoints (lower weight), priors, smoothness and the silhouette terms."""

    def __init__(self, problem: _Problem, targets: sil.SilhouetteTargets):
        self.problem, self.targets = problem, targets
        template = problem.template
        if problem.config.offsets:
            problem.offsets = RestOffsets(template)
        with torch.no_grad():
            verts = problem.vertices(problem.params())
            self.mm_per_px = sil.mm_per_pixel(verts.mean(1), targets)
        self.table, self.faces = sil.vertex_face_table(template.faces, template.num_verts)
        self.candidates: Tensor | None = None
        self.uncovered: Tensor | None = None

    def terms(self, it: int | None = None) -> tuple[dict[str, Tensor], Tensor]:
        """All terms at the current unknowns (the nearest vertices searched again when ``it`` says so)."""
        p, c = self.problem, self.problem.config
        params = p.params()
        verts = p.vertices(params)
        if self.candidates is None or it is None or it % c.reassign_every == 0:
            uv = sil.project(verts.detach(), self.targets.proj)[0]
            self.candidates = sil.nearest_candidates(uv, self.targets.samples)
            covered = sil.covered_samples(uv, self.targets.samples, self.candidates, self.table, self.faces)
            self.uncovered = (~covered).to(uv.dtype)
        out = p.terms(params)
        if p.offsets is not None:
            out.update(p.offsets.priors())
        out["outside"], out["cover"] = sil.silhouette_terms(
            verts, self.targets, self.candidates, self.uncovered, self.mm_per_px, c.outside_margin_mm,
            c.silhouette_robust_mm)
        return out, verts

    def __call__(self, it: int, free: bool) -> Tensor:
        return self.problem.weighted(self.terms(it)[0], self.problem.config.keypoints_in_silhouette)


def _adam(problem: _Problem, iters: int, lr: float, objective: Callable[[int, bool], Tensor], bar,
          warmup: int = 0) -> None:
    """``iters`` Adam steps on ``objective(it, free)`` with a cosine decay of the learning rate to 10 %."""
    if iters <= 0:
        return
    groups = [{"params": [problem.root, problem.body], "lr": lr}, {"params": [problem.transl], "lr": TRANSL_LR * lr},
              {"params": [problem.betas], "lr": BETAS_LR * lr}]
    if problem.offsets is not None:
        groups.append({"params": [problem.offsets.mm], "lr": OFFSETS_LR * lr})
    adam = torch.optim.Adam(groups)
    sched = torch.optim.lr_scheduler.LambdaLR(adam, lambda it: 0.1 + 0.45 * (1.0 + math.cos(math.pi * it / iters)))
    for it in range(iters):
        loss = objective(it, it >= warmup)
        adam.zero_grad(set_to_none=True)
        loss.backward()
        adam.step()
        sched.step()
        bar.update(1)
        if it % 10 == 0:
            bar.set_postfix(loss=f"{float(loss.detach()):.4g}", refresh=False)


# --------------------------------------------------------------------------------------------- the fit
def _check_inputs(template: SMPLTemplate, keypoints: np.ndarray, keypoint_conf: np.ndarray,
                  landmarks: BodyLandmarks | Sequence[int], cameras: Sequence[Camera] | None, masks: np.ndarray | None,
                  frame_ids: np.ndarray | None) -> tuple[BodyLandmarks, np.ndarray]:
    """The landmarks and frame times (N,) as int64; ValueError on inconsistent inputs."""
    sizes = check_shape("keypoints", keypoints, "N J 3")
    check_shape("keypoint_conf", keypoint_conf, "N J", sizes)
    if isinstance(landmarks, BodyLandmarks):
        if len(landmarks) != sizes["J"] or landmarks.weights.shape[1] != template.num_verts:
            raise ValueError(f"landmarks: expected {sizes['J']} landmarks of a body with {template.num_verts} "
                             f"vertices, got {len(landmarks)} of {landmarks.weights.shape[1]}")
    else:
        ids = np.asarray(list(landmarks), np.int64)
        if ids.shape != (sizes["J"],) or ids.size and not ((ids >= 0) & (ids < NUM_JOINTS)).all():
            raise ValueError(f"landmarks: expected {sizes['J']} SMPL joint indices in 0..{NUM_JOINTS - 1}, "
                             f"got {ids.tolist()}")
    if sizes["N"] == 0:
        raise ValueError("fit_body: no frames (keypoints has N = 0)")
    if not (_clean(keypoints, keypoint_conf)[1] > 0).any():
        raise ValueError("fit_body: no valid keypoint in any frame (every confidence is 0 or its point not finite)")
    times = np.arange(sizes["N"]) if frame_ids is None else np.asarray(frame_ids, np.int64)
    if times.shape != (sizes["N"],) or (np.diff(times) <= 0).any():
        raise ValueError(f"frame_ids: expected {sizes['N']} increasing frame numbers")
    landmarks = _as_landmarks(template, landmarks)
    if masks is not None:
        if cameras is None:
            raise ValueError("fit_body: masks need their cameras")
        check_shape("masks", masks, "N C H W", {"N": sizes["N"], "C": len(cameras)})
    return landmarks, times


def _result(problem: _Problem, stage: _SilhouetteStage | None, kp: np.ndarray, w: np.ndarray) -> BodyFitResult:
    """The fitted rows, per-keypoint errors, silhouette IoUs and the final terms."""
    with torch.no_grad():
        params = problem.params()
        if stage is not None:
            terms, verts = stage.terms()
            weight = problem.config.keypoints_in_silhouette
        else:
            terms, verts, weight = problem.terms(params), None, 1.0
        losses = {k: float(v) for k, v in terms.items()}
        losses["total"] = float(problem.weighted(terms, weight))
        points = problem.posed(params)[1].double().cpu().numpy()
    error = np.linalg.norm(points - kp, axis=2)
    error[w <= 0] = np.nan
    iou = None
    if stage is not None:
        with torch.no_grad():
            uv, depth = sil.project(verts, stage.targets.proj)
        rendered = sil.rasterize_silhouettes(uv.double().cpu().numpy(), depth.double().cpu().numpy(),
                                             problem.template.faces.cpu().numpy(), stage.targets.masks.shape[2:])
        iou = sil.silhouette_iou(rendered, stage.targets.masks)
    offsets = (problem.offsets.as_numpy() if problem.offsets is not None
               else np.zeros((problem.template.num_verts, 3)))
    return BodyFitResult(params.double().cpu().numpy(), error, iou, losses, offsets)


def fit_body(template: SMPLTemplate, keypoints: Real[np.ndarray, "N J 3"], keypoint_conf: Real[np.ndarray, "N J"],
             landmarks: BodyLandmarks | Sequence[int], cameras: Sequence[Camera] | None = None,
             masks: Bool[np.ndarray, "N C H W"] | UInt8[np.ndarray, "N C H W"] | None = None,
             config: BodyFitConfig = BodyFitConfig(), progress: bool = False,
             frame_ids: Integer[np.ndarray, "N"] | None = None) -> BodyFitResult:
    """Fit one shape and per-frame pose and translation of ``template`` to keypoints (and masks); module docstring.

    Args:
        template: the SMPL-layout body (world units mm: ``scale`` 1000); the fit runs on its device, in its dtype.
        keypoints: (N, J, 3) triangulated keypoints, world mm, N frames in temporal order (NaN where invalid).
        keypoint_conf: (N, J) confidence in [0, 1]; 0 = invalid.
        landmarks: the J body points the keypoints stand for (:func:`~deliffas.geometry.body_landmarks.body_landmarks`
            of ``template``), or (J,) SMPL joints (0..23).
        cameras: the C calibrated cameras of ``masks`` (needed with masks).
        masks: (N, C, H, W) bool or uint8 person masks (uint8 with values above 1: alphas, inside > 127), at the
            cameras' resolution or any with the same aspect; None = keypoints only.
        config: weights and steps.
        progress: show a tqdm bar.
        frame_ids: (N,) increasing frame numbers: the smoothness term links only consecutive ones (None: every
            frame follows the previous one).

    Returns:
        :class:`BodyFitResult`; ``silhouette_iou`` is None without masks.

    Raises:
        ValueError: shapes that disagree, joint ids outside 0..23 or landmarks of another body, no valid keypoint, masks without cameras or of
            another aspect than a camera.
    """
    landmarks, times = _check_inputs(template, keypoints, keypoint_conf, landmarks, cameras, masks, frame_ids)
    from tqdm.auto import tqdm  # a dependency; imported here so importing geometry stays light

    kp, w = _clean(keypoints, keypoint_conf)
    problem = _Problem(template, initial_body_params(template, kp, w, landmarks, times), kp, w, landmarks, times,
                       config)
    stage = None
    if masks is not None:
        targets = sil.prepare_silhouettes(masks, list(cameras), config.mask_height, config.mask_samples, config.seed,
                                          problem.transl)
    iters_sil = config.iters_silhouette if masks is not None else 0
    bar = tqdm(total=config.iters_keypoints + iters_sil, desc="fit body", disable=not progress)
    _adam(problem, config.iters_keypoints, config.lr, problem.keypoint_step, bar,
          warmup=int(round(config.warmup * config.iters_keypoints)))
    if masks is not None:
        stage = _SilhouetteStage(problem, targets)
        _adam(problem, iters_sil, 0.5 * config.lr, stage, bar)
    bar.close()
    return _result(problem, stage, kp, w)
