"""A license-free procedural SMPL motion: smooth, plausible joint rotations for synthetic captures.

Arms lowered from the T-pose and swinging, hips and knees stepping in place with a slowly turning
body, a breathing spine and a nodding head; each rotation is a seeded sum of a few slow sinusoids
(0.15-0.8 Hz), so consecutive frames at 25 fps differ by a few degrees. Joint axes follow SMPL's
rest frame (y-up, facing +z, the body's left at +x); rotations are axis-angle per joint as SMPL
takes them. The root stays near the origin (metres), y-up like the SMPL model itself.
"""

from __future__ import annotations

import numpy as np

from deliffas.io.body_models.amass import SMPLMotion
from deliffas.io.body_models.smpl import NUM_JOINTS

__all__ = ["procedural_smpl_motion"]

_J = {"pelvis": 0, "l_hip": 1, "r_hip": 2, "spine1": 3, "l_knee": 4, "r_knee": 5, "spine2": 6, "l_ankle": 7,
      "r_ankle": 8, "spine3": 9, "neck": 12, "l_collar": 13, "r_collar": 14, "head": 15, "l_shoulder": 16,
      "r_shoulder": 17, "l_elbow": 18, "r_elbow": 19}

# (joint, axis 0/1/2, base angle rad, amplitude rad): the motion's repertoire. Stepping flexes a hip
# forward about -x and its knee backward about +x; the two sides are half a cycle apart.
_CHANNELS = (
    ("l_shoulder", 2, -1.15, 0.25), ("r_shoulder", 2, 1.15, 0.25),   # arms down from the T-pose, swinging
    ("l_shoulder", 1, 0.0, 0.35), ("r_shoulder", 1, 0.0, 0.35),
    ("l_elbow", 1, 0.35, 0.3), ("r_elbow", 1, -0.35, 0.3),
    ("spine1", 1, 0.0, 0.15), ("spine2", 0, 0.05, 0.08), ("spine3", 2, 0.0, 0.08),
    ("neck", 0, 0.0, 0.12), ("head", 1, 0.0, 0.3),
    ("l_hip", 2, 0.06, 0.05), ("r_hip", 2, -0.06, 0.05),
)


def _wave(rng: np.random.Generator, t: np.ndarray, amplitude: float) -> np.ndarray:
    """Sum of three seeded slow sinusoids, scaled so its peak is about ``amplitude``."""
    out = np.zeros_like(t)
    for k in range(3):
        freq = rng.uniform(0.15, 0.8)
        out += rng.uniform(0.5, 1.0) / (k + 1) * np.sin(2 * np.pi * freq * t + rng.uniform(0, 2 * np.pi))
    return amplitude * out / 1.6


def procedural_smpl_motion(num_frames: int, seed: int = 0, fps: float = 25.0,
                           betas: np.ndarray | None = None) -> SMPLMotion:
    """A seeded SMPL motion of ``num_frames`` frames.

    Args:
        betas: (NB >= 10,) shape coefficients recorded with the motion (default zeros: the mean shape).

    Returns:
        poses (N, 72) axis-angle rad, trans (N, 3) metres, y-up; deterministic for (num_frames, seed, fps).
    """
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    rng = np.random.default_rng(seed)
    t = np.arange(num_frames) / float(fps)
    poses = np.zeros((num_frames, NUM_JOINTS, 3))
    for joint, axis, base, amplitude in _CHANNELS:
        poses[:, _J[joint], axis] = base + _wave(rng, t, amplitude)
    step = 2 * np.pi * rng.uniform(0.4, 0.7) * t + rng.uniform(0, 2 * np.pi)
    lift = 0.5 * (1 + np.sin(step))  # 0..1, the left leg's phase; the right one is half a cycle later
    for side, phase in (("l", lift), ("r", 1.0 - lift)):
        poses[:, _J[f"{side}_hip"], 0] = -0.55 * phase
        poses[:, _J[f"{side}_knee"], 0] = 1.0 * phase
        poses[:, _J[f"{side}_ankle"], 0] = -0.2 * phase
    poses[:, _J["pelvis"], 1] = 0.6 * np.sin(2 * np.pi * rng.uniform(0.03, 0.08) * t + rng.uniform(0, 2 * np.pi))
    trans = np.stack([0.05 * np.sin(0.7 * t + seed), 0.02 * np.abs(lift - 0.5),
                      0.05 * np.cos(0.5 * t + seed)], axis=1)
    shape = np.zeros(10) if betas is None else np.asarray(betas, np.float64)
    return SMPLMotion(poses.reshape(num_frames, 3 * NUM_JOINTS), trans, shape, float(fps))

