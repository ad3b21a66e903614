"""Masks made consistent across views: only the parts of a detector's mask where the tracked person is.

A single-view segmenter marks every person it sees (a bystander, a reflection) and sometimes a piece of
furniture. Across views, the person is where the triangulated keypoints project: :func:`person_mask` keeps
the connected parts of the mask that hold a reprojected keypoint (or lie within ``reach`` of one) and drops
the rest.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Float, UInt8

__all__ = ["person_mask", "MASK_THRESHOLD"]

MASK_THRESHOLD = 0.5
"""Person probability above which a pixel is the person."""


def person_mask(prob: Float[np.ndarray, "H W"], anchors: Float[np.ndarray, "K 2"] | None,
                reach: float = 0.03) -> UInt8[np.ndarray, "H W"]:
    """(H, W) uint8 alpha: the detector's probability x 255 on the components that hold the person.

    Args:
        prob: (H, W) float32 person probability in [0, 1].
        anchors: (K, 2) float pixels (corner convention) where the person is, e.g. the frame's triangulated
            keypoints projected into this view; None or empty = keep the largest component.
        reach: a component within this fraction of the image height of an anchor is kept.
    """
    import cv2

    solid = (prob > MASK_THRESHOLD).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(solid, connectivity=8)
    if count <= 1:
        return np.zeros(prob.shape, np.uint8)
    h, w = prob.shape
    keep = np.zeros(count, bool)
    pts = np.asarray(anchors, np.float64).reshape(-1, 2) if anchors is not None else np.zeros((0, 2))
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts):
        r = max(1, int(round(reach * h)))
        for x, y in pts:
            c, rr = int(np.clip(x, 0, w - 1)), int(np.clip(y, 0, h - 1))
            win = labels[max(0, rr - r): rr + r + 1, max(0, c - r): c + r + 1]
            keep[np.unique(win)] = True
        keep[0] = False
    if not keep.any():
        keep[1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))] = True
    support = cv2.dilate(keep[labels].astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return np.where(support, np.round(np.clip(prob, 0.0, 1.0) * 255.0), 0).astype(np.uint8)
