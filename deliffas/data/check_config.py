"""What ``check_subject`` samples and how it scores (:class:`CheckConfig`); light, so the CLI reads it without
torch."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.options import opt, positive_int

__all__ = ["CheckConfig"]


@dataclass(frozen=True)
class CheckConfig:
    """What ``check_subject`` samples and how it scores."""
    frames: int = opt(4, help="frames sampled per sequence, evenly spread", parse=positive_int)
    max_side: int = 128
    """Silhouettes and masks are compared at this many pixels on the longer image side (or less)."""
    offset_mm: float = 0.0
    """Score the outer shell at this offset instead of the template (0 = the template; measured in docs/data.md)."""
    tolerance_px: int = 1
    """Pixels within this distance of the silhouette's edge are not scored (aliasing, mask edges)."""
    min_iou: float = opt(0.8, help="a camera fails below this mean IoU")
    outlier_gap: float = 0.2
    """A camera whose IoU is this far below the median of the others is flagged (even above ``min_iou``)."""
    frame_offsets: int = 2
    """Pose/image frame offsets tried (+-1 .. +-N)."""
