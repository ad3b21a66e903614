"""The person in one camera's frames: a soft mask and 2-D body keypoints, from MediaPipe Pose (offline).

MediaPipe 0.10.21's wheel bundles ``pose_detection.tflite`` and ``pose_landmark_full.tflite`` (33 landmarks
and a person segmentation mask; Apache-2.0); ``model_complexity=1`` runs with nothing downloaded. One
:class:`PersonDetector` per camera runs in video mode (it tracks the person it found from frame to frame).
Its declared dependencies would replace ``opencv-contrib-python-headless`` by the GUI build and pull jax, so it
is installed without them: ``pip install 'deliffas[ingest]'`` (its runtime dependencies) and
``pip install --no-deps mediapipe==0.10.21`` (``make ingest-setup`` does both).

:data:`KEYPOINTS` names the body keypoints deliffas uses, each the MediaPipe landmarks it averages and the
body landmark it stands for.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, UInt8

from deliffas.optional import import_optional

__all__ = ["Keypoint", "KEYPOINTS", "KEYPOINT_NAMES", "BODY_LANDMARK_NAMES", "PersonDetection", "PersonDetector",
           "MissingExtraError", "require_detector", "DETECTOR_VERSION", "INSTALL_HINT"]

DETECTOR_VERSION = "0.10.21"
"""The MediaPipe release whose ``mp.solutions.pose`` runs offline (later ones download their models)."""
INSTALL_HINT = (f"pip install 'deliffas[ingest]' && pip install --no-deps mediapipe=={DETECTOR_VERSION} "
                "(or: make ingest-setup)")


class MissingExtraError(ValueError):
    """The optional detector is not installed; the message says what to type."""


@dataclass(frozen=True)
class Keypoint:
    """One body keypoint: its name, the MediaPipe landmarks averaged for it, the body landmark it stands for (a
    name of :data:`deliffas.geometry.body_landmarks.LANDMARK_NAMES`: an SMPL joint or a surface point)."""
    name: str
    landmarks: tuple[int, ...]
    body_landmark: str


KEYPOINTS = (
    Keypoint("l_hip", (23,), "l_hip"), Keypoint("r_hip", (24,), "r_hip"),
    Keypoint("l_knee", (25,), "l_knee"), Keypoint("r_knee", (26,), "r_knee"),
    Keypoint("l_ankle", (27,), "l_ankle"), Keypoint("r_ankle", (28,), "r_ankle"),
    Keypoint("l_heel", (29,), "l_heel"), Keypoint("r_heel", (30,), "r_heel"),
    Keypoint("l_toe", (31,), "l_toe"), Keypoint("r_toe", (32,), "r_toe"),
    Keypoint("nose", (0,), "nose"), Keypoint("l_ear", (7,), "l_ear"), Keypoint("r_ear", (8,), "r_ear"),
    Keypoint("l_shoulder", (11,), "l_shoulder"), Keypoint("r_shoulder", (12,), "r_shoulder"),
    Keypoint("l_elbow", (13,), "l_elbow"), Keypoint("r_elbow", (14,), "r_elbow"),
    Keypoint("l_wrist", (15,), "l_wrist"), Keypoint("r_wrist", (16,), "r_wrist"),
)
"""The J = 19 keypoints, in order (left = the person's left, as in MediaPipe and SMPL). MediaPipe's foot index
(31, 32) is the tip of the foot and its ears and nose lie on the skin: they stand for surface landmarks, not for
SMPL's foot and head joints (which lie inside the body, several cm away)."""
KEYPOINT_NAMES = tuple(k.name for k in KEYPOINTS)
BODY_LANDMARK_NAMES = tuple(k.body_landmark for k in KEYPOINTS)


@dataclass(frozen=True)
class PersonDetection:
    """What the detector saw in one image.

    Attributes:
        mask: (H, W) float32 person probability in [0, 1] (zeros when no person was found).
        keypoints: (J, 2) float64 pixels, deliffas convention (pixel corners on integers), of :data:`KEYPOINTS`.
        conf: (J,) float64 in [0, 1] (MediaPipe's visibility; 0 when no person was found).
    """
    mask: Float[np.ndarray, "H W"]
    keypoints: Float[np.ndarray, "J 2"]
    conf: Float[np.ndarray, "J"]

    @property
    def found(self) -> bool:
        return bool(self.conf.max(initial=0.0) > 0)


def require_detector():
    """The ``mediapipe`` module with its pose solution; :class:`MissingExtraError` saying what to install."""
    os.environ.setdefault("GLOG_minloglevel", "2")  # MediaPipe's C++ start-up lines on stderr
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    try:
        mp = import_optional("mediapipe", "deliffas ingest needs MediaPipe")
    except ImportError as err:
        raise MissingExtraError(f"deliffas ingest needs the optional detector (MediaPipe {DETECTOR_VERSION}), "
                                f"which does not import ({err.__cause__ or err}); install it: {INSTALL_HINT}") from None
    if not hasattr(mp, "solutions") or not hasattr(mp.solutions, "pose"):
        raise MissingExtraError(f"mediapipe {getattr(mp, '__version__', '?')} has no mp.solutions.pose (removed after "
                                f"{DETECTOR_VERSION}, whose models ship in the wheel); install it: {INSTALL_HINT}")
    return mp


class PersonDetector:
    """MediaPipe Pose (full model, segmentation on) over one camera's frames in order.

    Args:
        video: track the person from frame to frame (frames of one camera in order); False = every image
            on its own.
    """

    def __init__(self, video: bool = True):
        mp = require_detector()
        self._pose = mp.solutions.pose.Pose(static_image_mode=not video, model_complexity=1,
                                            enable_segmentation=True, smooth_landmarks=video,
                                            smooth_segmentation=video, min_detection_confidence=0.5,
                                            min_tracking_confidence=0.5)

    def __call__(self, rgb: UInt8[np.ndarray, "H W 3"]) -> PersonDetection:
        """The person in ``rgb`` (H, W, 3) uint8 RGB."""
        h, w = rgb.shape[:2]
        result = self._pose.process(np.ascontiguousarray(rgb))
        if result.pose_landmarks is None:
            return PersonDetection(np.zeros((h, w), np.float32), np.zeros((len(KEYPOINTS), 2)),
                                   np.zeros(len(KEYPOINTS)))
        lm = np.array([(p.x, p.y, p.visibility) for p in result.pose_landmarks.landmark], np.float64)  # (33, 3)
        xy = np.stack([lm[list(k.landmarks), :2].mean(axis=0) for k in KEYPOINTS]) * (w, h)
        conf = np.array([lm[list(k.landmarks), 2].min() for k in KEYPOINTS])
        mask = (np.asarray(result.segmentation_mask, np.float32) if result.segmentation_mask is not None
                else np.zeros((h, w), np.float32))
        return PersonDetection(np.clip(mask, 0.0, 1.0), xy, np.clip(conf, 0.0, 1.0))

    def close(self) -> None:
        self._pose.close()

    def __enter__(self) -> "PersonDetector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
