"""A license-free body in the exact SMPL model layout, built from the procedural implicit-body machinery.

SMPL itself is not shipped (its license forbids redistribution); this body lets every SMPL code path
(``SMPLTemplate``, ``smpl_spec``, fitting, AMASS motions) run on files deliffas can make itself. It is
the zero level set of a smooth union of round cones and ellipsoids placed on SMPL's 24 joints in a
T-pose (``deliffas.geometry.procedural``'s primitives), meshed by marching tetrahedra, decimated and
remeshed to ``target_verts``. It is *not* SMPL's mesh: its vertex count, face list and blend shapes
are its own; only the layout (arrays, shapes, kinematic tree, joint order, conventions) is SMPL's.

Conventions as SMPL: metres, y-up, facing +z, the body's left side at +x, pelvis joint near the
origin. The arrays:

- ``J_regressor`` (24, V): each row a convex combination (weights >= 0, sum 1) of the vertices
  around the joint, solved so the regressed rest joints equal the joints the body was built on.
- ``weights`` (V, 24): smooth skinning weights from radius-normalised distances to each joint's
  bone (the segment the joint's rotation moves), <= 4 influences, rows summing to 1.
- ``shapedirs`` (V, 3, 10): hand-made linear shape directions (one unit of beta ~ 1-4 cm):
  0 height, 1 girth, 2 arm length, 3 shoulder width, 4 belly, 5 leg length, 6 head size,
  7 hip width, 8 chest depth, 9 torso length.
- ``posedirs`` (V, 3, 207): corrective bulges: near each non-root joint j, vertices move along
  their normal by ``POSE_BULGE_M * falloff * (3 - trace(R_j))``, i.e. linear in SMPL's pose
  feature ``R_j - I`` (its diagonal), growing as ``2 (1 - cos angle)`` with the bend.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from deliffas.io.obj import ObjData, write_obj
from deliffas.io.body_models.smpl import NUM_JOINTS, NUM_POSE_BASIS, SMPLModelData, write_smpl_model
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.marching_tets import marching_tetrahedra
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.variants import decimate_mesh, remesh_isotropic
# the implicit-body primitives are procedural.py's private helpers; shared here rather than copied
from deliffas.geometry.implicit_body import Primitive, sdf_grid

__all__ = [
    "SMPL_JOINT_NAMES",
    "SMPL_PARENTS",
    "SHAPE_DIRECTIONS",
    "procedural_smpl_joints",
    "procedural_smpl",
    "procedural_smpl_atlas",
    "make_procedural_smpl",
]

log = logging.getLogger(__name__)

SMPL_JOINT_NAMES = (
    "pelvis", "l_hip", "r_hip", "spine1", "l_knee", "r_knee", "spine2", "l_ankle", "r_ankle", "spine3",
    "l_foot", "r_foot", "neck", "l_collar", "r_collar", "head", "l_shoulder", "r_shoulder", "l_elbow",
    "r_elbow", "l_wrist", "r_wrist", "l_hand", "r_hand",
)
"""SMPL's 24 joints in model order."""
SMPL_PARENTS = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21])
"""(24,) int64 parent of each joint, -1 for the root."""
SHAPE_DIRECTIONS = ("height", "girth", "arm_length", "shoulder_width", "belly", "leg_length", "head_size",
                    "hip_width", "chest_depth", "torso_length")
"""What each of the 10 ``shapedirs`` columns changes (one unit of beta ~ 1-4 cm)."""

GRID_M = 0.012
"""Marching-tetrahedra grid spacing, metres."""
SMOOTH_K_M = 0.028
"""Smooth-min blend radius between primitives, metres."""
SKIN_SIGMA = 0.25
"""Skin falloff: w = exp(-(q - q_min)^2 / (2 sigma^2)), q = distance to the bone / bone radius."""
MAX_INFLUENCES = 4
POSE_BULGE_M = 0.004
"""Normal offset per unit of (3 - trace(R)) at a joint (~8 mm at a 90 degree bend)."""
REGRESSOR_NEIGHBOURS = 40
"""Vertices around a joint its regressor row may use."""

# T-pose joints of the nominal body (metres, y-up, facing +z, left at +x); right side mirrors left.
_LEFT_JOINTS = {
    "l_hip": (0.085, -0.075, -0.005), "l_knee": (0.100, -0.465, 0.005), "l_ankle": (0.100, -0.865, -0.035),
    "l_foot": (0.110, -0.925, 0.085), "l_collar": (0.070, 0.425, -0.015), "l_shoulder": (0.175, 0.445, -0.015),
    "l_elbow": (0.440, 0.445, -0.025), "l_wrist": (0.690, 0.445, -0.020), "l_hand": (0.775, 0.440, -0.020),
}
_CENTRE_JOINTS = {"pelvis": (0.0, 0.0, 0.0), "spine1": (0.0, 0.105, -0.015), "spine2": (0.0, 0.235, 0.0),
                  "spine3": (0.0, 0.300, 0.010), "neck": (0.0, 0.505, -0.020), "head": (0.0, 0.580, 0.020)}


def procedural_smpl_joints(seed: int = 0) -> np.ndarray:
    """(24, 3) float64 rest joints of the body built for ``seed`` (metres, T-pose).

    The seed scales the nominal body by +-2 % (height) and its width by +-4 %.
    """
    height, width = _seed_scales(seed)
    out = np.zeros((NUM_JOINTS, 3))
    for name, p in _CENTRE_JOINTS.items():
        out[SMPL_JOINT_NAMES.index(name)] = p
    for name, (x, y, z) in _LEFT_JOINTS.items():
        out[SMPL_JOINT_NAMES.index(name)] = (x, y, z)
        out[SMPL_JOINT_NAMES.index("r" + name[1:])] = (-x, y, z)
    return out * np.array([width, height, width]) * height


def _seed_scales(seed: int) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    return 1.0 + rng.uniform(-0.02, 0.02), 1.0 + rng.uniform(-0.04, 0.04)


def _j(joints: np.ndarray, name: str) -> np.ndarray:
    return joints[SMPL_JOINT_NAMES.index(name)]


# --------------------------------------------------------------------------------------------- implicit body
def _primitives(joints: np.ndarray) -> list[Primitive]:
    """Primitives of the T-pose body, in mm (the procedural SDF helpers work in mm)."""
    J = {n: _j(joints, n) * 1000.0 for n in SMPL_JOINT_NAMES}
    eye = np.eye(3)
    prims = [
        Primitive("pelvis", "ell", J["pelvis"] + (0, -25, 5), rot=eye, radii=np.array([150, 110, 100])),
        Primitive("belly", "ell", J["spine1"] + (0, 40, 15), rot=eye, radii=np.array([135, 120, 95])),
        Primitive("chest", "ell", J["spine3"] + (0, 40, 0), rot=eye, radii=np.array([160, 150, 105])),
        Primitive("chest", "cone", J["l_shoulder"] + (-25, -25, 0), J["r_shoulder"] + (25, -25, 0), 60, 60),
        Primitive("neck", "cone", J["neck"] - (0, 40, 0), J["head"] + (0, 30, 0), 52, 46),
        Primitive("head", "ell", J["head"] + (0, 95, 5), rot=eye, radii=np.array([78, 108, 95])),
        Primitive("head", "ell", J["head"] + (0, 75, 100), rot=eye, radii=np.array([14, 25, 18])),  # nose
    ]
    for s in ("l", "r"):
        sh, el, wr, hand = J[f"{s}_shoulder"], J[f"{s}_elbow"], J[f"{s}_wrist"], J[f"{s}_hand"]
        hip, kn, an, foot = J[f"{s}_hip"], J[f"{s}_knee"], J[f"{s}_ankle"], J[f"{s}_foot"]
        side = 1.0 if s == "l" else -1.0
        prims += [
            Primitive("shoulder", "ell", sh + (0, -8, 0), rot=eye, radii=np.array([58, 56, 56])),
            Primitive("arm", "cone", sh, el, 52, 42),
            Primitive("arm", "cone", el, wr, 40, 30),
            Primitive("hand", "ell", wr + (hand - wr) * 1.2, rot=eye, radii=np.array([100, 22, 46])),
            Primitive("leg", "cone", hip + (0, 25, 0), kn, 88, 55),
            Primitive("leg", "cone", kn, an, 52, 38),
            Primitive("leg", "ell", kn + 0.3 * (an - kn) + (0, 0, -20), rot=eye, radii=np.array([46, 110, 46])),
            Primitive("foot", "ell", np.array([foot[0] - side * 5, an[1] - 45, 0.5 * (an[2] + foot[2]) + 10]), rot=eye,
                  radii=np.array([45, 40, 125])),
        ]
    return prims


def _mesh(joints: np.ndarray, target_verts: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed T-pose mesh (metres) with about ``target_verts`` vertices."""
    values, origin = sdf_grid(_primitives(joints), GRID_M * 1000.0, SMOOTH_K_M * 1000.0)
    verts, faces = marching_tetrahedra(values, origin, GRID_M * 1000.0)
    target_faces = 2 * target_verts - 4  # a closed genus-0 mesh: F = 2 V - 4
    log.info("procedural_smpl: marching tetrahedra %d faces, decimating to %d", len(faces), target_faces)
    verts, faces = decimate_mesh(verts, faces, target_faces)
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    edge = float(np.sqrt(4 * area / (np.sqrt(3) * target_faces)))
    verts, faces = remesh_isotropic(verts, faces, edge, 4)
    return verts / 1000.0, faces


# --------------------------------------------------------------------------------------------- bones and weights
def _bones(joints: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Per joint (in SMPL order): the segment its rotation moves and that bone's radius, metres."""
    J = {n: _j(joints, n) for n in SMPL_JOINT_NAMES}
    up, fwd = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    segs = {
        "pelvis": (J["pelvis"] - 0.06 * up, J["pelvis"] + 0.03 * up, 0.13),
        "spine1": (J["spine1"], J["spine2"], 0.12),
        "spine2": (J["spine2"], J["spine3"], 0.13),
        "spine3": (J["spine3"], J["neck"] - 0.04 * up, 0.14),
        "neck": (J["neck"], J["head"], 0.05),
        "head": (J["head"] + 0.04 * up, J["head"] + 0.14 * up, 0.09),
    }
    for s in ("l", "r"):
        out = np.array([1.0 if s == "l" else -1.0, 0.0, 0.0])
        segs.update({
            f"{s}_hip": (J[f"{s}_hip"], J[f"{s}_knee"], 0.075),
            f"{s}_knee": (J[f"{s}_knee"], J[f"{s}_ankle"], 0.045),
            f"{s}_ankle": (J[f"{s}_ankle"], J[f"{s}_foot"] - 0.03 * fwd, 0.045),
            f"{s}_foot": (J[f"{s}_foot"], J[f"{s}_foot"] + 0.06 * fwd, 0.035),
            f"{s}_collar": (J[f"{s}_collar"], J[f"{s}_shoulder"] - 0.02 * out, 0.06),
            f"{s}_shoulder": (J[f"{s}_shoulder"], J[f"{s}_elbow"], 0.045),
            f"{s}_elbow": (J[f"{s}_elbow"], J[f"{s}_wrist"], 0.034),
            f"{s}_wrist": (J[f"{s}_wrist"], J[f"{s}_hand"], 0.035),
            f"{s}_hand": (J[f"{s}_hand"], J[f"{s}_hand"] + 0.08 * out, 0.03),
        })
    return [segs[n] for n in SMPL_JOINT_NAMES]


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (N,) of points p (N, 3) to segment ab, and the closest points (N, 3)."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    closest = a + t[:, None] * ab
    return np.linalg.norm(p - closest, axis=1), closest


def _skin_weights(verts: np.ndarray, bones) -> np.ndarray:
    """(V, 24) smooth weights, <= MAX_INFLUENCES per vertex, rows summing to 1."""
    q = np.stack([_segment_distance(verts, a, b)[0] / r for a, b, r in bones], axis=1)  # (V, 24)
    dense = np.exp(-((q - q.min(axis=1, keepdims=True)) ** 2) / (2 * SKIN_SIGMA ** 2))
    keep = np.argsort(-dense, axis=1, kind="stable")[:, :MAX_INFLUENCES]
    weights = np.zeros_like(dense)
    np.put_along_axis(weights, keep, np.take_along_axis(dense, keep, axis=1), axis=1)
    weights[weights < 1e-3] = 0.0
    return weights / weights.sum(axis=1, keepdims=True)


def _regressor(verts: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(24, V) rows of non-negative weights summing to 1 whose weighted vertex mean is the joint.

    Per joint: start from Gaussian weights w0 on its nearest vertices, then apply the smallest
    w0-weighted correction that meets the four linear constraints (mean = joint, sum = 1) exactly;
    vertices whose weight would turn negative are dropped and the correction is solved again on
    the rest (a small active-set loop). Without a solution, more neighbours are tried.
    """
    out = np.zeros((NUM_JOINTS, len(verts)))
    target = np.append(joints, np.ones((NUM_JOINTS, 1)), axis=1)  # (24, 4)
    for j, joint in enumerate(joints):
        d = np.linalg.norm(verts - joint, axis=1)
        order = np.argsort(d, kind="stable")
        for k in (REGRESSOR_NEIGHBOURS, 2 * REGRESSOR_NEIGHBOURS, 4 * REGRESSOR_NEIGHBOURS):
            row = _convex_row(verts[order[:k]], d[order[:k]], target[j])
            if row is not None:
                out[j, order[:k]] = row
                break
        else:
            raise RuntimeError(f"procedural_smpl: joint {SMPL_JOINT_NAMES[j]} is outside its vertices' hull")
    return out


def _convex_row(points: np.ndarray, dist: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """(k,) weights >= 0 with [points.T; 1] @ w == target (4,), near Gaussian weights; None if not found."""
    w0 = np.exp(-0.5 * (dist / dist.max()) ** 2)
    w0 /= w0.sum()
    C = np.vstack([points.T, np.ones(len(points))])  # (4, k)
    active = np.ones(len(points), bool)
    for _ in range(len(points)):
        D = np.where(active, w0, 0.0)
        if active.sum() < 4:
            return None
        lhs = (C * D) @ C.T
        w = w0 * active + D * (C.T @ np.linalg.solve(lhs, target - C @ (w0 * active)))
        if (w >= -1e-12).all():
            w = np.clip(w, 0.0, None)
            return w if np.abs(C @ w - target).max() < 1e-9 else None
        active &= w > 0
    return None


# --------------------------------------------------------------------------------------------- blend shapes
def _smooth_step(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _shapedirs(verts: np.ndarray, joints: np.ndarray, weights: np.ndarray, bones) -> np.ndarray:
    """(V, 3, 10) shape directions (``SHAPE_DIRECTIONS``), metres per unit of beta."""
    J = {n: _j(joints, n) for n in SMPL_JOINT_NAMES}
    x, y, z = verts.T
    V = len(verts)
    out = np.zeros((V, 3, 10))
    w = {n: weights[:, i] for i, n in enumerate(SMPL_JOINT_NAMES)}
    arm = sum(w[f"{s}_{p}"] for s in "lr" for p in ("shoulder", "elbow", "wrist", "hand"))
    leg = sum(w[f"{s}_{p}"] for s in "lr" for p in ("hip", "knee", "ankle", "foot"))
    torso = 1.0 - arm - leg
    head = w["head"] + 0.5 * w["neck"]
    foot_y = verts[:, 1].min()
    # 0 height: stretch y about the feet, 2.5 % per unit
    out[:, 1, 0] = 0.025 * (y - foot_y)
    # 1 girth: away from the bone axis (the skinning-weighted closest bone point), 8 % per unit
    closest = np.zeros_like(verts)
    for i, (a, b, _) in enumerate(bones):
        closest += weights[:, i:i + 1] * _segment_distance(verts, a, b)[1]
    out[:, :, 1] = 0.08 * (verts - closest) * (1.0 - 0.8 * head)[:, None]
    # 2 arm length: arms slide outwards in x beyond the shoulder, 4 % of the arm per unit
    sx = abs(J["l_shoulder"][0])
    out[:, 0, 2] = 0.04 * np.sign(x) * np.clip(np.abs(x) - sx, 0.0, None) * arm
    # 3 shoulder width: everything beyond the collar moves outwards by up to 1.5 cm
    out[:, 0, 3] = 0.015 * np.sign(x) * _smooth_step(np.abs(x), 0.05, sx) * _smooth_step(y, J["spine3"][1], J["neck"][1])
    # 4 belly: the front of the lower torso moves forwards, up to 2.5 cm
    belly = np.exp(-0.5 * ((y - J["spine1"][1] - 0.04) / 0.09) ** 2) * np.clip(z / 0.1, 0.0, 1.0) * torso
    out[:, 2, 4] = 0.025 * belly
    # 5 leg length: everything below the hips moves down, more towards the feet (4 %)
    out[:, 1, 5] = -0.04 * np.clip(J["l_hip"][1] - y, 0.0, None)
    # 6 head size: scale about the head centre, 6 %
    centre = J["head"] + (0.0, 0.09, 0.0)
    out[:, :, 6] = 0.06 * (verts - centre) * head[:, None]
    # 7 hip width: the pelvis and legs move outwards in x, up to 1.5 cm
    hips = _smooth_step(-y, -J["spine1"][1], -J["l_hip"][1] + 0.05) * (1.0 - arm)
    out[:, 0, 7] = 0.015 * np.tanh(x / 0.05) * hips
    # 8 chest depth: the chest front and back move apart, up to 2 cm each
    chest = np.exp(-0.5 * ((y - J["spine3"][1] - 0.05) / 0.08) ** 2) * torso
    out[:, 2, 8] = 0.02 * np.tanh((z - J["spine3"][2]) / 0.05) * chest
    # 9 torso length: everything above spine2 moves up by 2.5 cm (smoothly from spine1)
    out[:, 1, 9] = 0.025 * _smooth_step(y, J["spine1"][1], J["spine2"][1])
    return out


def _posedirs(verts: np.ndarray, faces: np.ndarray, joints: np.ndarray, bones) -> np.ndarray:
    """(V, 3, 207) corrective bulges, linear in the diagonal of each joint's ``R - I``."""
    normals = vertex_normals(verts, faces)
    out = np.zeros((len(verts), 3, NUM_POSE_BASIS))
    for j in range(1, NUM_JOINTS):
        radius = bones[j][2]
        falloff = np.exp(-0.5 * (np.linalg.norm(verts - joints[j], axis=1) / (1.5 * radius)) ** 2)
        bulge = -POSE_BULGE_M * falloff[:, None] * normals  # per unit of trace(R - I) (<= 0 when bent)
        for diag in (0, 4, 8):
            out[:, :, 9 * (j - 1) + diag] = bulge
    return out


# --------------------------------------------------------------------------------------------- assembly
def procedural_smpl(seed: int = 0, target_verts: int = 2000) -> SMPLModelData:
    """The procedural body in the SMPL layout (module docstring), metres.

    Args:
        seed: body proportions (+-2 % height, +-4 % width); the same seed gives the same arrays.
        target_verts: vertex budget, 500..20000 (the remesher lands within ~10 % of it).

    Returns:
        SMPLModelData: ``v_template`` (V, 3), ``shapedirs`` (V, 3, 10), ``posedirs`` (V, 3, 207),
        ``J_regressor`` (24, V), ``weights`` (V, 24), ``parents`` (24,) = ``SMPL_PARENTS``, ``faces`` (F, 3).
    """
    if not 500 <= target_verts <= 20000:
        raise ValueError(f"target_verts: expected 500..20000, got {target_verts}")
    joints = procedural_smpl_joints(seed)
    verts, faces = _mesh(joints, target_verts)
    bones = _bones(joints)
    weights = _skin_weights(verts, bones)
    return SMPLModelData(
        v_template=verts, shapedirs=_shapedirs(verts, joints, weights, bones),
        posedirs=_posedirs(verts, faces, joints, bones), J_regressor=_regressor(verts, joints), weights=weights,
        parents=SMPL_PARENTS.astype(np.int64), faces=faces.astype(np.int64))


def procedural_smpl_atlas(data: SMPLModelData, resolution: int = 1024) -> UVAtlas:
    """Per-corner xatlas uvs of the rest mesh (``faces`` row f <-> ``face_uvs`` row f)."""
    return UVAtlas.from_mesh(data.v_template, data.faces, resolution=resolution)


def make_procedural_smpl(out_dir: str | os.PathLike, seed: int = 0, target_verts: int = 2000) -> Path:
    """Write ``smpl_procedural.npz`` (official key names) and ``smpl_procedural_uv.obj`` into ``out_dir``.

    Both load through the same code as a user's SMPL file:
    ``SMPLTemplate(npz, uv_obj=obj)`` / ``smpl_spec(npz, uv_obj=obj)``.

    Returns:
        Path of the ``.npz`` model file (the OBJ sits next to it).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = procedural_smpl(seed, target_verts)
    atlas = procedural_smpl_atlas(data)
    model = out / "smpl_procedural.npz"
    write_smpl_model(model, data)
    write_obj(out / "smpl_procedural_uv.obj",
              ObjData(data.v_template, data.faces, np.array(atlas.uvs), np.array(atlas.face_uvs)), precision=8)
    return model
