"""The motion record: a template's pose parameters per frame, whatever file or template they came from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, Integer

__all__ = ["Motion"]


@dataclass(frozen=True)
class Motion:
    """A template's pose parameters per frame: a frame number and D parameter values per row.

    Every template kind is driven by one (a DynaCap ``.motion`` file reads into it directly; an
    SMPL motion becomes one through ``geometry.smpl_params.smpl_to_motion``).

    Attributes:
        frames: (N,) int64 frame number of each row (absolute, as written; ``row_of`` maps back).
        dofs: (N, D) float64 parameter values in the template's order and units (a DynaCap skeleton:
            its DOF order, metres for root translations, radians for angles).
    """

    frames: Integer[np.ndarray, "N"]
    dofs: Float[np.ndarray, "N D"]

    @property
    def num_frames(self) -> int:
        return int(self.dofs.shape[0])

    def row_of(self, frame: int) -> int:
        """Row index holding ``frame``; KeyError when the motion lacks it."""
        rows = np.nonzero(self.frames == frame)[0]
        if len(rows) == 0:
            raise KeyError(f"frame {frame} not in motion (frames {int(self.frames.min())}..{int(self.frames.max())})")
        return int(rows[0])
