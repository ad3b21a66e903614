"""A license-free procedural human character built in memory and written as a complete DynaCap character.

The body is the zero level set of a smooth union of capsules, round cones and ellipsoids placed on a
Skeletool V1.0 skeleton in an A-pose, meshed by marching tetrahedra (one closed manifold) and
decimated to the face budget (``deliffas.geometry.variants.decimate_mesh``). Skin weights come from
radius-normalised distances to the bone segments, labels from the dominating primitive (LIP labels
of dynacap-formats.md 1.8, with 12 = skirt as the loose-garment region), UVs from xatlas
(``deliffas.geometry.atlas``) and the texture is painted procedurally from 3D positions, so it is
seamless across UV charts. The skeleton's DOF names are a subset of the DDC skeleton's, with the
same sign conventions, so ``deliffas.geometry.motion_gen`` drives both.

World: y-up, mm, feet on y = 0, the character faces -z, its left side is at -x (as DDC's zero pose).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from deliffas.io.formats.dynacap.character import Character, CharacterFiles, ObjData, Skin, write_character
from deliffas.io.infra.files import claim_output
from deliffas.io.formats.dynacap.skeleton import Dof, Joint, Skeleton
from deliffas.geometry.variants import decimate_mesh, remesh_isotropic, sparsify_weights
from deliffas.geometry.atlas import UVAtlas, uv_texel_table
from deliffas.geometry.skeleton import SkeletonFK
from deliffas.geometry.implicit_body import Primitive, sdf_grid
from deliffas.geometry.marching_tets import CUBE_CORNERS, marching_tetrahedra
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.procedural_config import ProceduralConfig

__all__ = [
    "PROCEDURAL_DOF_NAMES",
    "LABELS",
    "procedural_skeleton",
    "procedural_character",
    "ProceduralConfig",
    "make_procedural_character",
]

log = logging.getLogger(__name__)

HEIGHT_MM = 1750.0
"""Nominal standing height of the procedural character (seed jitter +-2 %)."""
GRID_MM = 10.0
"""Marching-tetrahedra grid spacing."""
SMOOTH_K_MM = 28.0
"""Smooth-min blend radius between primitives."""
REMESH_ITERATIONS = 6
"""Isotropic remeshing passes after decimation (minimum triangle angle ~20 degrees)."""
SKIN_SIGMA = 0.22
"""Skin falloff: w_b = exp(-(q_b - q_min)^2 / (2 sigma^2)), q = distance / bone radius."""
MIN_SKIN_WEIGHT = 1e-3

LABELS = {"hair": 2, "upper_clothes": 5, "skirt": 12, "face": 13, "left_arm": 14, "right_arm": 15,
          "left_leg": 16, "right_leg": 17, "left_shoe": 18, "right_shoe": 19}
"""LIP labels written to ``segmentation.txt`` (dynacap-formats.md 1.8); 12 marks the loose skirt."""

# name, limits, ((joint, weight), ...): same names, order and signs as the DDC skeleton's body DOFs
_DOFS_CENTRE = [
    ("translate_x", None, (("Root_tx", 1000.0),)),
    ("translate_y", None, (("Root_ty", 1000.0),)),
    ("translate_z", None, (("Root_tz", 1000.0),)),
    ("rotate_y", None, (("Root_ry", 3.0),)),
    ("rotate_z", None, (("Root_rz", 3.0),)),
    ("rotate_x", None, (("Root_rx", 3.0),)),
    ("spine_twist", None, (("Lumbar_ry", 0.2), ("Thorax_ry", 0.3), ("Chest_ry", 0.5))),
    ("spine_lean", (-0.55, 0.55), (("Lumbar_rz", 0.3), ("Thorax_rz", 0.35), ("Chest_rz", 0.35))),
    ("spine_bend", (-0.8, 0.25), (("Lumbar_rx", 0.4), ("Thorax_rx", 0.35), ("Chest_rx", 0.25))),
    ("head_twist", (-1.4, 1.4), (("Neck_ry", 0.333), ("Head_ry", 0.667))),
    ("head_lean", (-0.5, 0.5), (("Neck_rz", 0.8), ("Head_rz", 0.2))),
    ("head_bend", (-0.65, 0.65), (("Neck_rx", 0.7), ("Head_rx", 0.3))),
]
_DOFS_ARM = [  # {S} = Left / Right, {s} = left / right
    ("{s}_clavicle_y", (-0.4, 0.5), (("{S}Clavicle_ry", 1.0),)),
    ("{s}_clavicle_z", (-0.05, 0.4), (("{S}Clavicle_rz", 1.0),)),
    ("{s}_shoulder_y", None, (("{S}Arm_ry", 1.0),)),
    ("{s}_shoulder_z", (-10.0, 10.0), (("{S}Arm_rz", 1.0),)),
    ("{s}_shoulder_twist", None, (("{S}Arm_rx", 1.0),)),
    ("{s}_elbow", (-2.7, -0.1), (("{S}ForeArm_ry", 1.0),)),
    ("{s}_forearm_twist", (-2.7, 1.8), (("{S}ForeArmRoll", 1.0),)),
    ("{s}_hand_y", (-0.5, 0.5), (("{S}Hand_ry", 1.0),)),
    ("{s}_hand_z", (-1.3, 1.3), (("{S}Hand_rz", 1.0),)),
]
_DOFS_LEG = [
    ("{s}_hip_x", (-10.0, 10.0), (("{S}UpLeg_rx", 1.0),)),
    ("{s}_hip_z", None, (("{S}UpLeg_rz", 1.0),)),
    ("{s}_hip_y", None, (("{S}UpLeg_ry", 1.0),)),
    ("{s}_knee", (-3.0, 0.2), (("{S}Leg_rx", 1.0),)),
    ("{s}_ankle_x", (-0.4, 0.7), (("{S}Foot_rx", 3.0),)),
    ("{s}_ankle_z", (-0.25, 0.25), (("{S}Foot_rz", 1.0),)),
]


def _side(entries, S, s):
    return [(n.format(s=s), lim, tuple((j.format(S=S), w) for j, w in refs)) for n, lim, refs in entries]


_DOF_TABLE = (_DOFS_CENTRE + _side(_DOFS_ARM, "Left", "left") + _side(_DOFS_ARM, "Right", "right")
              + _side(_DOFS_LEG, "Left", "left") + _side(_DOFS_LEG, "Right", "right"))
PROCEDURAL_DOF_NAMES = tuple(name for name, _, _ in _DOF_TABLE)
"""DOF names of the procedural skeleton, in motion column order (a subset of the DDC skeleton's)."""

_REST = {"left_shoulder_z": -0.8, "right_shoulder_z": -0.8, "left_elbow": -0.15, "right_elbow": -0.15,
         "left_hip_z": -0.07, "right_hip_z": -0.07}
"""Rest (A-pose) DOF values; every other DOF rests at 0."""

X, Y, Z = np.eye(3)


def _joints(H: float) -> list[Joint]:
    """Joints of the zero pose (T-pose, arms along -+x, facing -z), offsets scaled to height H.

    Joint order puts each bone's carrier joint last among the joints its name prefixes (the C++
    bone -> joint rule of dynacap-formats.md 1.5).
    """
    def J(name, jtype, parent, offset, axis):
        return Joint(name, jtype, parent, np.asarray(offset, np.float64) * 1.0, np.asarray(axis, np.float64))

    out = [
        J("Root_tx", "prismatic", "none", (0, 0.548 * H, 0), X),
        J("Root_ty", "prismatic", "Root_tx", (0, 0, 0), Y),
        J("Root_tz", "prismatic", "Root_ty", (0, 0, 0), Z),
        J("Root_ry", "revolute", "Root_tz", (0, 0, 0), Y),
        J("Root_rz", "revolute", "Root_ry", (0, 0, 0), Z),
        J("Root_rx", "revolute", "Root_rz", (0, 0, 0), X),
    ]
    parent = "Root_rx"
    for name, dy in (("Lumbar", 0.06), ("Thorax", 0.075), ("Chest", 0.08), ("Neck", 0.083), ("Head", 0.05)):
        out += [J(f"{name}_ry", "revolute", parent, (0, dy * H, 0), Y),
                J(f"{name}_rz", "revolute", f"{name}_ry", (0, 0, 0), Z),
                J(f"{name}_rx", "revolute", f"{name}_rz", (0, 0, 0), X)]
        parent = f"{name}_rx"
    out.append(J("Crown", "revolute", "Head_rx", (0, 0.1 * H, 0), Y))
    for S, m in (("Left", 1.0), ("Right", -1.0)):
        # mirror x -> -x: offsets (x, y, z) -> (-x, y, z); rotation axes (pseudo-vectors) -> (x, -y, -z)
        off = lambda x, y, z: (m * x * H, y * H, z * H)  # noqa: E731
        ax = lambda a: np.array([a[0], m * a[1], m * a[2]])  # noqa: E731
        out += [
            J(f"{S}Clavicle_ry", "revolute", "Chest_rx", off(-0.012, 0.055, 0), ax(-Y)),
            J(f"{S}Clavicle_rz", "revolute", f"{S}Clavicle_ry", (0, 0, 0), ax(-Z)),
            J(f"{S}Arm_rz", "revolute", f"{S}Clavicle_rz", off(-0.097, 0, 0), ax(-Z)),
            J(f"{S}Arm_ry", "revolute", f"{S}Arm_rz", (0, 0, 0), ax(Y)),
            J(f"{S}Arm_rx", "revolute", f"{S}Arm_ry", (0, 0, 0), ax(X)),
            J(f"{S}ForeArm_ry", "revolute", f"{S}Arm_rx", off(-0.165, 0, 0), ax(Y)),
            J(f"{S}ForeArmRoll", "revolute", f"{S}ForeArm_ry", (0, 0, 0), ax(-X)),
            J(f"{S}Hand_ry", "revolute", f"{S}ForeArmRoll", off(-0.145, 0, 0), ax(Y)),
            J(f"{S}Hand_rz", "revolute", f"{S}Hand_ry", (0, 0, 0), ax(-Z)),
            J(f"{S}Fingertips", "revolute", f"{S}Hand_rz", off(-0.105, 0, 0), ax(Y)),
            J(f"{S}UpLeg_rx", "revolute", "Root_rx", off(-0.054, -0.034, 0), ax(-X)),
            J(f"{S}UpLeg_rz", "revolute", f"{S}UpLeg_rx", (0, 0, 0), ax(Z)),
            J(f"{S}UpLeg_ry", "revolute", f"{S}UpLeg_rz", (0, 0, 0), ax(Y)),
            J(f"{S}Leg_rx", "revolute", f"{S}UpLeg_ry", off(0, -0.243, 0), ax(X)),
            J(f"{S}Foot_rx", "revolute", f"{S}Leg_rx", off(0, -0.23, 0), ax(X)),
            J(f"{S}Foot_rz", "revolute", f"{S}Foot_rx", (0, 0, 0), ax(Z)),
            J(f"{S}Toes", "revolute", f"{S}Foot_rz", off(0, -0.045, -0.085), ax(X)),
        ]
    return out


def procedural_skeleton(height_mm: float = HEIGHT_MM) -> tuple[Skeleton, np.ndarray]:
    """The procedural Skeletool V1.0 skeleton and its rest (A-pose) DOF values.

    Root translation: prismatic Root_tx/ty/tz driven by translate_x/y/z with weight 1000
    (DOF metres -> mm); root rotations Root_ry/rz/rx by rotate_y/z/x with weight 3, as DDC.

    Returns:
        skeleton, rest_dofs (D,) float64 in the skeleton's DOF order.
    """
    joints = _joints(float(height_mm))
    dofs = tuple(Dof(name, lim, refs) for name, lim, refs in _DOF_TABLE)
    skel = Skeleton(tuple(joints), (), (), dofs)
    rest = np.array([_REST.get(name, 0.0) for name in PROCEDURAL_DOF_NAMES])
    return skel, rest


# --------------------------------------------------------------------------------------------- implicit body
def _body_primitives(P: dict[str, np.ndarray], R: dict[str, np.ndarray], H: float, girth: float) -> list[Primitive]:
    """Primitives of the A-pose body from rest joint positions P and rotations R (mm)."""
    g = girth * H / HEIGHT_MM
    s = H / HEIGHT_MM
    up = Y
    prims = [
        Primitive("pelvis", "ell", P["Root_rx"] + (0, 5 * s, 5 * s), rot=np.eye(3), radii=np.array([150, 118, 102]) * g),
        Primitive("belly", "ell", P["Lumbar_rx"] + (0, 35 * s, 0), rot=np.eye(3), radii=np.array([132, 120, 94]) * g),
        Primitive("chest", "ell", P["Thorax_rx"] + (0, 85 * s, 0), rot=np.eye(3), radii=np.array([160, 160, 104]) * g),
        Primitive("chest", "cone", P["LeftArm_rx"] + (30 * s, -22 * s, 0), P["RightArm_rx"] + (-30 * s, -22 * s, 0),
              58 * g, 58 * g),
        Primitive("neck", "cone", P["Neck_rx"] - 30 * s * up, P["Head_rx"] + 30 * s * up, 50 * g, 46 * g),
        Primitive("head", "ell", P["Head_rx"] + (0, 80 * s, -8 * s), rot=np.eye(3), radii=np.array([76, 100, 92]) * s),
        Primitive("head", "ell", P["Head_rx"] + (0, 62 * s, -92 * s), rot=np.eye(3), radii=np.array([13, 24, 17]) * s),
        Primitive("head", "ell", P["Head_rx"] + (0, 20 * s, -50 * s), rot=np.eye(3), radii=np.array([52, 42, 52]) * s),
    ]
    for S in ("Left", "Right"):
        sh, el, wr, tip = P[f"{S}Arm_rx"], P[f"{S}ForeArmRoll"], P[f"{S}Hand_rz"], P[f"{S}Fingertips"]
        hip, kn, an, toe = P[f"{S}UpLeg_ry"], P[f"{S}Leg_rx"], P[f"{S}Foot_rz"], P[f"{S}Toes"]
        hand_axis = (tip - wr) / np.linalg.norm(tip - wr)
        width = R[f"{S}Hand_rz"][:, 2]
        width = width - (width @ hand_axis) * hand_axis
        width /= np.linalg.norm(width)
        hand_rot = np.stack([hand_axis, width, np.cross(hand_axis, width)], axis=1)
        foot_axis = toe - an
        foot_axis = np.array([foot_axis[0], 0.0, foot_axis[2]])
        foot_axis /= np.linalg.norm(foot_axis)
        foot_rot = np.stack([np.cross(up, foot_axis), up, foot_axis], axis=1)
        prims += [
            Primitive(f"{S}_shoulder", "ell", sh + (0, -8 * s, 0), rot=np.eye(3), radii=np.array([58, 55, 55]) * g),
            Primitive(f"{S}_upperarm", "cone", sh, el, 54 * g, 43 * g),
            Primitive(f"{S}_forearm", "cone", el, wr, 41 * g, 30 * g),
            Primitive(f"{S}_hand", "ell", wr + 0.45 * (tip - wr), rot=hand_rot,
                  radii=np.array([0.58 * np.linalg.norm(tip - wr), 48 * s, 24 * s])),
            Primitive(f"{S}_thigh", "cone", hip + (0, 20 * s, 0), kn, 86 * g, 54 * g),
            Primitive(f"{S}_shin", "cone", kn, an, 51 * g, 36 * g),
            Primitive(f"{S}_shin", "ell", kn + 0.3 * (an - kn) + (0, 0, 22 * s), rot=np.eye(3),
                  radii=np.array([46, 110, 46]) * g),
            Primitive(f"{S}_foot", "ell", an + (0, -42 * s, -58 * s), rot=foot_rot, radii=np.array([46, 42, 128]) * s),
        ]
    return prims


# --------------------------------------------------------------------------------------------- skinning, labels
def _bone_segments(P: dict[str, np.ndarray], H: float, girth: float) -> list[tuple[str, np.ndarray, np.ndarray, float]]:
    """(bone name, segment start, segment end, radius mm) of every skin bone."""
    g = girth * H / HEIGHT_MM
    s = H / HEIGHT_MM
    segs = [
        ("Root", P["Root_rx"] - (0, 60 * s, 0), P["Lumbar_rx"], 130 * g),
        ("Lumbar", P["Lumbar_rx"], P["Thorax_rx"], 120 * g),
        ("Thorax", P["Thorax_rx"], P["Chest_rx"], 140 * g),
        ("Chest", P["Chest_rx"], P["Neck_rx"], 140 * g),
        ("Neck", P["Neck_rx"], P["Head_rx"], 50 * g),
        ("Head", P["Head_rx"] + (0, 30 * s, 0), P["Crown"] - (0, 60 * s, 0), 90 * s),
    ]
    for S in ("Left", "Right"):
        segs += [
            (f"{S}Clavicle", P[f"{S}Clavicle_rz"], P[f"{S}Arm_rx"], 55 * g),
            (f"{S}Arm", P[f"{S}Arm_rx"], P[f"{S}ForeArmRoll"], 45 * g),
            (f"{S}ForeArm", P[f"{S}ForeArmRoll"], P[f"{S}Hand_rz"], 32 * g),
            (f"{S}Hand", P[f"{S}Hand_rz"], P[f"{S}Fingertips"], 30 * s),
            (f"{S}UpLeg", P[f"{S}UpLeg_ry"], P[f"{S}Leg_rx"], 70 * g),
            (f"{S}Leg", P[f"{S}Leg_rx"], P[f"{S}Foot_rz"], 45 * g),
            (f"{S}Foot", P[f"{S}Foot_rz"], P[f"{S}Toes"], 45 * s),
        ]
    return segs


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (N,) of points p (N, 3) to segment ab and the segment parameter t (N,)."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1), t


def _skin_weights(verts: np.ndarray, segs) -> Skin:
    """Smooth skin weights from radius-normalised distances to the bone segments, <= 6 influences."""
    q = np.stack([_segment_distance(verts, a, b)[0] / r for _, a, b, r in segs], axis=1)  # (V, Bn)
    dense = np.exp(-((q - q.min(axis=1, keepdims=True)) ** 2) / (2 * SKIN_SIGMA ** 2))
    dense[dense < MIN_SKIN_WEIGHT] = 0.0
    idx, w = sparsify_weights(dense)
    return Skin(tuple(name for name, *_ in segs), idx, w)


def _labels(verts: np.ndarray, prims: list[Primitive], P: dict[str, np.ndarray], H: float) -> tuple[np.ndarray, np.ndarray]:
    """LIP segmentation (V,) and hand segmentation (V,) (0 none, 1 left hand, 2 right hand)."""
    s = H / HEIGHT_MM
    d = np.stack([p.sdf(verts) for p in prims], axis=1)
    part = np.array([p.part for p in prims])[np.argmin(d, axis=1)]
    y = verts[:, 1]
    waist_y = P["Lumbar_rx"][1] + 20 * s
    hem_y = 0.5 * (P["LeftUpLeg_ry"][1] + P["LeftLeg_rx"][1]) + 20 * s  # skirt hem above mid-thigh
    head_c = P["Head_rx"] + (0, 80 * s, -8 * s)
    labels = np.full(len(verts), LABELS["upper_clothes"], np.int64)
    labels[np.isin(part, ["pelvis", "belly"]) & (y < waist_y)] = LABELS["skirt"]
    rel = verts - head_c
    face_region = (rel[:, 2] < -25 * s) & (rel[:, 1] < 55 * s)  # front of the head, below the hairline
    is_head = np.isin(part, ["head", "neck"])
    labels[is_head] = np.where(face_region[is_head] | (part[is_head] == "neck") | (rel[is_head, 1] < -40 * s),
                               LABELS["face"], LABELS["hair"])
    hand = np.zeros(len(verts), np.int64)
    for S, side in (("Left", "left"), ("Right", "right")):
        sleeve = _segment_distance(verts, P[f"{S}Arm_rx"], P[f"{S}ForeArmRoll"])[1] < 0.6
        arm = np.isin(part, [f"{S}_upperarm", f"{S}_forearm", f"{S}_hand"])
        labels[arm & ~((part == f"{S}_upperarm") & sleeve)] = LABELS[f"{side}_arm"]
        labels[(part == f"{S}_shoulder")] = LABELS["upper_clothes"]
        leg = np.isin(part, [f"{S}_thigh", f"{S}_shin"])
        labels[leg] = np.where(y[leg] > hem_y, LABELS["skirt"], LABELS[f"{side}_leg"])
        labels[part == f"{S}_foot"] = LABELS[f"{side}_shoe"]
        hand[part == f"{S}_hand"] = 1 if side == "left" else 2
    return labels, hand


# --------------------------------------------------------------------------------------------- texture
_SKIN_TONES = np.array([[0.96, 0.80, 0.69], [0.89, 0.69, 0.56], [0.78, 0.57, 0.44], [0.60, 0.42, 0.30],
                        [0.42, 0.29, 0.20]])
_HAIR = np.array([[0.09, 0.07, 0.06], [0.25, 0.16, 0.09], [0.55, 0.40, 0.22], [0.45, 0.20, 0.10]])
_CLOTH = np.array([[0.80, 0.15, 0.15], [0.15, 0.35, 0.75], [0.15, 0.55, 0.30], [0.95, 0.75, 0.15],
                   [0.55, 0.25, 0.65], [0.95, 0.95, 0.92], [0.10, 0.12, 0.18], [0.95, 0.50, 0.20]])


def _value_noise(p: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at points p (N, 3) with feature size ``scale`` mm."""
    x = p / scale
    i = np.floor(x)
    f = x - i
    f = f * f * (3 - 2 * f)
    out = np.zeros(len(p))
    for c in CUBE_CORNERS:  # 8 lattice corners, vectorised over points
        n = i + c
        h = np.sin(n[:, 0] * 127.1 + n[:, 1] * 311.7 + n[:, 2] * 74.7 + seed * 17.31) * 43758.5453
        h = h - np.floor(h)
        w = np.prod(np.where(c == 1, f, 1 - f), axis=1)
        out += w * h
    return out


def _paint(points: np.ndarray, labels: np.ndarray, P: dict[str, np.ndarray], H: float,
           palette: dict[str, np.ndarray], seed: int) -> np.ndarray:
    """Procedural RGB (N, 3) in [0, 1] of surface points (N, 3) with labels (N,)."""
    s = H / HEIGHT_MM
    x, y, z = points.T
    fine = _value_noise(points, 6.0, seed)
    coarse = _value_noise(points, 70.0, seed + 1)
    skin = palette["skin"] * (0.94 + 0.1 * coarse[:, None] + 0.04 * fine[:, None])
    rgb = skin.copy()
    # hair: streaks stretched along y
    streak = _value_noise(points * np.array([1.0, 0.15, 1.0]), 4.0, seed + 2)
    hair = palette["hair"] * (0.7 + 0.6 * streak[:, None])
    # upper clothes: horizontal stripes with a fabric weave
    stripes = (np.sin(2 * np.pi * y / (55 * s)) > 0.35)[:, None]
    weave = 0.9 + 0.1 * (np.sin(x * 1.3) * np.sin(y * 1.3) > 0)[:, None]
    shirt = np.where(stripes, palette["shirt2"], palette["shirt"]) * weave * (0.92 + 0.08 * fine[:, None])
    # skirt: a plaid of two colours
    plaid = ((np.abs(np.sin(np.pi * x / (45 * s))) < 0.25)
             | (np.abs(np.sin(np.pi * (y + z) / (45 * s))) < 0.25))[:, None]
    check = (((np.floor(x / (90 * s)) + np.floor(y / (90 * s))) % 2) == 0)[:, None]
    skirt = np.where(plaid, palette["skirt2"], palette["skirt"] * np.where(check, 1.0, 0.82))
    skirt = skirt * (0.93 + 0.07 * fine[:, None])
    shoe = np.where((y < 14 * s)[:, None], np.array([0.92, 0.92, 0.9]), palette["shoe"] * (0.85 + 0.3 * fine[:, None]))
    rgb = np.where((labels == LABELS["hair"])[:, None], hair, rgb)
    rgb = np.where((labels == LABELS["upper_clothes"])[:, None], shirt, rgb)
    rgb = np.where((labels == LABELS["skirt"])[:, None], skirt, rgb)
    rgb = np.where(np.isin(labels, [LABELS["left_shoe"], LABELS["right_shoe"]])[:, None], shoe, rgb)
    # face: eyes, brows and lips on the front of the head
    head_c = P["Head_rx"] + (0, 80 * s, -8 * s)
    rel = points - head_c
    front = (labels == LABELS["face"]) & (rel[:, 2] < -40 * s)
    for side in (-1.0, 1.0):
        ex, ey = side * 30 * s, 18 * s
        r = np.hypot(rel[:, 0] - ex, rel[:, 1] - ey)
        rgb[front & (r < 12 * s)] = (0.95, 0.95, 0.93)
        rgb[front & (r < 6 * s)] = palette["eyes"]
        rgb[front & (r < 2.5 * s)] = (0.02, 0.02, 0.02)
        brow = front & (np.abs(rel[:, 1] - ey - 20 * s) < 4 * s) & (np.abs(rel[:, 0] - ex) < 17 * s)
        rgb[brow] = palette["hair"]
    lips = front & (np.abs(rel[:, 1] + 44 * s) < 5 * s) & (np.abs(rel[:, 0]) < 22 * s)
    rgb[lips] = palette["skin"] * np.array([1.0, 0.55, 0.55])
    return np.clip(rgb, 0.0, 1.0)


def _palette(rng: np.random.Generator) -> dict[str, np.ndarray]:
    c = rng.permutation(len(_CLOTH))
    return {
        "skin": _SKIN_TONES[rng.integers(len(_SKIN_TONES))],
        "hair": _HAIR[rng.integers(len(_HAIR))],
        "shirt": _CLOTH[c[0]], "shirt2": _CLOTH[c[1]] * 0.9 + 0.1,
        "skirt": _CLOTH[c[2]], "skirt2": _CLOTH[c[3]] * 0.7,
        "shoe": np.array([0.12, 0.10, 0.09]) + rng.uniform(0, 0.15, 3),
        "eyes": np.array([[0.25, 0.15, 0.08], [0.20, 0.35, 0.55], [0.25, 0.40, 0.25]])[rng.integers(3)],
    }


def _bake_texture(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray, atlas, size: int, paint,
                  label_fn) -> np.ndarray:
    """(S, S, 3) uint8 RGB atlas image: each valid texel painted at its 3D point (row 0 = top).

    A texel takes its face's label when the face's three corners agree, otherwise ``label_fn`` of
    its 3D point, so label borders are smooth curves rather than triangle staircases.
    """
    table = uv_texel_table(atlas, size, gutter=4)
    img = np.full((size * size, 3), 0.5)
    valid = table.valid.ravel()
    face = table.face.ravel()[valid]
    bary = table.bary.reshape(-1, 3)[valid].astype(np.float64)
    corners = faces[face]  # (N, 3)
    pts = (bary[..., None] * verts[corners]).sum(axis=1)
    lab = labels[corners[:, 0]]
    mixed = (labels[corners[:, 1]] != lab) | (labels[corners[:, 2]] != lab)
    lab[mixed] = label_fn(pts[mixed])
    img[valid] = paint(pts, lab)
    return np.round(img.reshape(size, size, 3) * 255).astype(np.uint8)


def _encode_png(rgb: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:  # pragma: no cover - cv2 failure
        raise RuntimeError("cv2.imencode failed to encode the texture")
    return buf.tobytes()


# --------------------------------------------------------------------------------------------- assembly
def _rest_frames(skel: Skeleton, rest: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    import torch

    with torch.no_grad():
        G = SkeletonFK(skel, dtype=torch.float64)(torch.tensor(rest)[None])[0].numpy()
    names = skel.joint_names
    return {n: G[i, :3, 3] for i, n in enumerate(names)}, {n: G[i, :3, :3] for i, n in enumerate(names)}


def _shift_root(skel: Skeleton, dy: float) -> Skeleton:
    import dataclasses

    joints = list(skel.joints)
    joints[0] = dataclasses.replace(joints[0], offset=joints[0].offset + np.array([0.0, dy, 0.0]))
    return dataclasses.replace(skel, joints=tuple(joints))


def _seed_params(seed: int) -> tuple[float, float, dict[str, np.ndarray]]:
    """Height (mm), girth factor and colour palette drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    H = HEIGHT_MM * (1 + rng.uniform(-0.02, 0.02))
    girth = 1 + rng.uniform(-0.05, 0.05)
    return H, girth, _palette(rng)


def procedural_character(seed: int = 0, target_faces: int = 8000, name: str = "procedural",
                         texture_size: int = 1024) -> Character:
    """Build the procedural character in memory.

    Args:
        seed: body proportions (+-2 % height, +-5 % girth), colours and pattern phases.
        target_faces: face budget of the template (5k-20k recommended; decimation lands on it).
        name: file stem used in the record's nominal paths (nothing is written).
        texture_size: side of the square texture atlas, texels.

    Returns:
        A ``Character`` whose ``path``/``files`` are nominal (``<name>.character`` etc., not on
        disk yet); the texture PNG bytes are in ``extra["texture_png"]``. Write it with
        ``make_procedural_character`` or ``write_character(dir, c, name, texture_png=...)``.
    """
    if not 500 <= target_faces <= 200_000:
        raise ValueError(f"target_faces: expected 500..200000, got {target_faces}")
    H, girth, palette = _seed_params(seed)
    skel, rest = procedural_skeleton(H)
    P, R = _rest_frames(skel, rest)
    prims = _body_primitives(P, R, H, girth)
    values, origin = sdf_grid(prims, GRID_MM, SMOOTH_K_MM)
    verts, faces = marching_tetrahedra(values, origin, GRID_MM)
    log.info("procedural: marching tetrahedra %d faces, decimating to %d", len(faces), target_faces)
    verts, faces = decimate_mesh(verts, faces, target_faces)
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    edge = float(np.sqrt(4 * area / (np.sqrt(3) * target_faces)))  # equilateral faces of that size tile the area
    verts, faces = remesh_isotropic(verts, faces, edge, REMESH_ITERATIONS)
    # feet on y = 0: move the mesh and the root together
    dy = -float(verts[:, 1].min())
    verts[:, 1] += dy
    skel = _shift_root(skel, dy)
    P = {k: v + (0.0, dy, 0.0) for k, v in P.items()}
    prims = _body_primitives(P, R, H, girth)

    skin = _skin_weights(verts, _bone_segments(P, H, girth))
    labels, hand = _labels(verts, prims, P, H)
    atlas = UVAtlas.from_mesh(verts, faces, resolution=texture_size, padding=4)
    paint = lambda pts, lab: _paint(pts, lab, P, H, palette, seed)  # noqa: E731
    texture = _bake_texture(verts, faces, labels, atlas, texture_size, paint, lambda pts: _labels(pts, prims, P, H)[0])
    colors = paint(verts, labels)
    normals = vertex_normals(verts, faces)
    mesh = ObjData(verts, faces, np.asarray(atlas.uvs).copy(), np.asarray(atlas.face_uvs).copy(), colors,
                   normals, faces.copy())
    graph_faces = int(np.clip(target_faces // 7, 600, 1800))
    gv, gf = decimate_mesh(verts, faces, graph_faces)
    graph = ObjData(gv, gf)
    files = CharacterFiles(Path(f"{name}.skeleton"), Path(f"{name}.obj"), Path(f"{name}.skin"), Path(f"{name}.motion"))
    return Character(
        path=Path(f"{name}.character"), files=files, skeleton=skel, mesh=mesh, skin=skin,
        rest_dofs=rest, segmentation=labels, hand_segmentation=hand, graph=graph, texture=None,
        extra={"texture_png": _encode_png(texture), "seed": int(seed), "height_mm": float(verts[:, 1].max())},
    )


def make_procedural_character(config: ProceduralConfig) -> Path:
    """Build the procedural character and write it as a DynaCap character folder.

    Writes ``<name>.character/.skeleton/.obj/.obj.mtl/.png/.skin/.motion``, ``segmentation.txt``,
    ``hand_segmentation.txt`` and ``<name>_graph.obj`` into ``config.out_dir`` (a non-empty folder is
    refused unless ``config.overwrite`` and it holds an earlier ``<name>.character``).

    Returns:
        Path of the ``.character`` file.
    """
    name = config.name
    out = claim_output(config.out_dir, config.overwrite, f"{name}.character", "a procedural character")
    c = procedural_character(config.seed, config.target_faces, name, config.texture_size)
    return write_character(out, c, name, texture_png=c.extra["texture_png"])
