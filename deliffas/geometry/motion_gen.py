"""Smooth procedural DOF trajectories for any skeleton whose DOF names follow the DDC naming.

Each known DOF gets a sum of sinusoids around its rest value, with amplitudes given in *joint*
units (radians, or mm for the root translation) and converted to DOF units through the skeleton's
own DOF weights, so the same seed produces the same joint motion on the DDC skeleton and on the
procedural one (``deliffas.geometry.procedural``). Random phases and frequencies are drawn per DOF
*name* (seeded by the seed and the name), never by column order. DOFs the generator does not know
(fingers, scales, ``*_knee_varus``...) stay at their rest value; values are clipped to the
skeleton's DOF limits. The root yaw (``rotate_y``) turns slowly, so every side of the body is seen.
"""

from __future__ import annotations

import zlib
from typing import Literal

import numpy as np

from deliffas.io.motion import Motion
from deliffas.io.formats.dynacap.skeleton import Skeleton

__all__ = ["MotionStyle", "procedural_motion", "known_dof_names", "MAX_YAW_RATE"]

MotionStyle = Literal["walk_in_place", "dance", "mixed"]

MAX_YAW_RATE = 2 * np.pi / 250.0
"""Largest root yaw change per frame, rad (a full turn in 10 s at 25 fps)."""

GAIT_HZ = 0.9
"""Stride frequency of ``walk_in_place``."""
MIX_PERIOD_S = 8.0
"""``mixed`` fades walk -> dance -> walk with this period."""

# Walk: DOF name -> (amplitude in joint units, harmonic of the stride, phase offset in radians).
# Signs follow the DDC skeleton: hip_x < 0 swings the leg forward, knee/elbow < 0 flex,
# shoulder_y > 0 swings the arm backwards (so it opposes the leg of the same side).
_WALK = {
    "translate_x": (20.0, 1, 0.0),
    "translate_y": (12.0, 2, np.pi / 2),
    "rotate_z": (0.02, 1, 0.0),
    "rotate_x": (0.02, 2, 0.0),
    "spine_twist": (0.10, 1, np.pi),
    "spine_lean": (0.04, 1, 0.0),
    "spine_bend": (0.03, 2, 0.0),
    "head_twist": (0.05, 1, 0.0),
    "head_bend": (0.03, 2, np.pi),
    "left_shoulder_y": (0.35, 1, 0.0),
    "right_shoulder_y": (0.35, 1, np.pi),
    "left_elbow": (0.15, 1, np.pi),
    "right_elbow": (0.15, 1, 0.0),
    "left_hip_x": (-0.40, 1, 0.0),
    "right_hip_x": (-0.40, 1, np.pi),
    "left_ankle_x": (0.12, 1, np.pi / 2),
    "right_ankle_x": (0.12, 1, 3 * np.pi / 2),
    "left_hip_z": (0.03, 1, 0.0),
    "right_hip_z": (0.03, 1, np.pi),
}
_KNEE_WALK = 0.75  # peak knee flexion (rad) during the swing of that leg

# Dance: DOF name -> amplitude in joint units; each DOF sums three random sinusoids.
_DANCE = {
    "translate_x": 80.0, "translate_y": 25.0, "translate_z": 80.0,
    "rotate_z": 0.05, "rotate_x": 0.05,
    "spine_twist": 0.30, "spine_lean": 0.15, "spine_bend": 0.15,
    "head_twist": 0.35, "head_lean": 0.15, "head_bend": 0.2,
    "left_clavicle_y": 0.1, "left_clavicle_z": 0.12, "right_clavicle_y": 0.1, "right_clavicle_z": 0.12,
    "left_shoulder_y": 0.6, "left_shoulder_z": 0.7, "left_shoulder_twist": 0.4,
    "right_shoulder_y": 0.6, "right_shoulder_z": 0.7, "right_shoulder_twist": 0.4,
    "left_elbow": 0.6, "right_elbow": 0.6,
    "left_forearm_twist": 0.4, "right_forearm_twist": 0.4,
    "left_hand_y": 0.25, "left_hand_z": 0.4, "right_hand_y": 0.25, "right_hand_z": 0.4,
    "left_hip_x": 0.35, "left_hip_z": 0.12, "left_hip_y": 0.15,
    "right_hip_x": 0.35, "right_hip_z": 0.12, "right_hip_y": 0.15,
    "left_knee": 0.4, "right_knee": 0.4,
    "left_ankle_x": 0.15, "left_ankle_z": 0.08, "right_ankle_x": 0.15, "right_ankle_z": 0.08,
}
_ONE_SIDED = {"left_elbow": -1.0, "right_elbow": -1.0, "left_knee": -1.0, "right_knee": -1.0}
"""Dance offsets of these DOFs only go one way (flexion), so they never hyper-extend."""
_DANCE_HZ = (0.15, 0.7)


def known_dof_names() -> set[str]:
    """DOF names the generator animates (others stay at rest)."""
    return set(_WALK) | set(_DANCE) | {"rotate_y", "left_knee", "right_knee"}


def _name_rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])


def _walk(name: str, t: np.ndarray, seed: int, phase0: float) -> np.ndarray | None:
    """Joint-unit offset of DOF ``name`` at times t (s) for walking in place, or None if unknown."""
    phi = 2 * np.pi * GAIT_HZ * t + phase0
    if name in ("left_knee", "right_knee"):
        shift = 0.0 if name.startswith("left") else np.pi
        return -_KNEE_WALK * (0.5 + 0.5 * np.sin(phi + shift + np.pi / 3)) ** 2
    if name == "translate_z":
        r = _name_rng(seed, name)
        return 25.0 * np.sin(2 * np.pi * 0.07 * t + r.uniform(0, 2 * np.pi))
    if name not in _WALK:
        return None
    amp, harmonic, offset = _WALK[name]
    return amp * np.sin(harmonic * phi + offset)


def _dance(name: str, t: np.ndarray, seed: int) -> np.ndarray | None:
    if name not in _DANCE:
        return None
    r = _name_rng(seed, name)
    freqs = r.uniform(*_DANCE_HZ, size=3)
    phases = r.uniform(0, 2 * np.pi, size=3)
    weights = r.dirichlet(np.ones(3))  # sum 1: |offset| <= amplitude
    x = (weights[:, None] * np.sin(2 * np.pi * freqs[:, None] * t + phases[:, None])).sum(0)
    amp = _DANCE[name]
    if name in _ONE_SIDED:
        return _ONE_SIDED[name] * amp * 0.5 * (1 + x)
    return amp * x


def procedural_motion(skeleton: Skeleton, num_frames: int, seed: int = 0, style: MotionStyle = "walk_in_place",
                      rest_dofs: np.ndarray | None = None, fps: float = 25.0, turns: float = 1.0,
                      first_frame: int = 0) -> Motion:
    """Smooth, plausible DOF trajectories for a DDC-named skeleton.

    Args:
        skeleton: any skeleton whose DOF names follow the DDC naming (the DDC one, the procedural one).
        num_frames: N.
        seed: phases, frequencies and (dance) amplitudes; the same seed gives the same joint motion
            for a DOF name on every skeleton.
        style: ``walk_in_place`` (gait cycle, arms swinging), ``dance`` (three random sinusoids per
            DOF, larger amplitudes) or ``mixed`` (fades between the two, period ``MIX_PERIOD_S``).
        rest_dofs: (D,) DOF values the motion oscillates around (the character's rest pose); zeros
            when None.
        fps: frames per second the frequencies refer to.
        turns: full turns of the root yaw over the sequence; the yaw rate is capped at
            ``MAX_YAW_RATE`` per frame, so short sequences turn less.
        first_frame: frame index of the first row.

    Returns:
        Motion with frames first_frame..first_frame+N-1 and dofs (N, D) in DOF units.
    """
    if num_frames < 1:
        raise ValueError(f"num_frames: expected >= 1, got {num_frames}")
    if style not in ("walk_in_place", "dance", "mixed"):
        raise ValueError(f"style: expected 'walk_in_place', 'dance' or 'mixed', got {style!r}")
    D = skeleton.num_dofs
    rest = np.zeros(D) if rest_dofs is None else np.asarray(rest_dofs, np.float64)
    if rest.shape != (D,):
        raise ValueError(f"rest_dofs: expected shape ({D},), got {rest.shape}")
    t = np.arange(num_frames) / float(fps)
    phase0 = float(np.random.default_rng(int(seed) & 0xFFFFFFFF).uniform(0, 2 * np.pi))
    if style == "mixed":
        mix = 0.5 - 0.5 * np.cos(2 * np.pi * t / MIX_PERIOD_S)  # 0 = walk, 1 = dance
    else:
        mix = np.full(num_frames, 1.0 if style == "dance" else 0.0)
    dofs = np.tile(rest, (num_frames, 1))
    for d, dof in enumerate(skeleton.dofs):  # a loop over DOFs, vectorised over frames
        gain = float(sum(abs(w) for _, w in dof.joints))
        if gain == 0.0:
            continue
        if dof.name == "rotate_y":
            rate = min(2 * np.pi * turns / max(num_frames - 1, 1), MAX_YAW_RATE)
            offset = rate * np.arange(num_frames)
        else:
            walk = _walk(dof.name, t, seed, phase0)
            dance = _dance(dof.name, t, seed)
            if walk is None and dance is None:
                continue
            walk = np.zeros(num_frames) if walk is None else walk
            dance = np.zeros(num_frames) if dance is None else dance
            offset = (1 - mix) * walk + mix * dance
        sign = np.sign(sum(w for _, w in dof.joints)) or 1.0
        dofs[:, d] = rest[d] + sign * offset / gain
        if dof.limits is not None:
            lo, hi = dof.limits
            dofs[:, d] = np.clip(dofs[:, d], min(lo, rest[d]), max(hi, rest[d]))
    return Motion(np.arange(first_frame, first_frame + num_frames, dtype=np.int64), dofs)
