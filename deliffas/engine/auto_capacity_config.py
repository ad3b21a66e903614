"""How ``auto_capacity`` searches (:class:`AutoCapacityConfig`, :class:`Candidate`); light, so the CLI reads it
without torch."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Mapping, Sequence

from deliffas.engine.config_fields import TEST_SPLITS
from deliffas.options import opt

__all__ = ["AutoCapacityConfig", "Candidate"]


@dataclass(frozen=True)
class Candidate:
    """One model capacity to try."""

    name: str
    """Folder name of its run (``candidates/<name>``) and its label in the record."""
    overrides: dict = field(default_factory=dict)
    """``ModelConfig`` fields replacing the preset's (nested dicts for ``unet``/``mlp``), merged over
    ``TrainConfig.model_overrides``."""


@dataclass(frozen=True)
class AutoCapacityConfig:
    """How ``auto_capacity`` searches."""

    tolerance_db: float = opt(0.5, help="auto-capacity tolerance in dB: candidates within it of the best validation "
                                        "PSNR are kept")
    candidates: Sequence[Candidate | Mapping] | None = None
    """Capacities to try: ``Candidate``s or override dicts (named by their content). None = the
    ``default_ladder`` of the run's model and preset."""
    iters: int | None = None
    """Training iterations of every candidate; None = ``TrainConfig.iters``."""
    split: Literal["validation", "train"] = "validation"
    """Selection split (module docstring); the test splits are refused."""
    validation_cameras: int = 1
    """Least number of training cameras every candidate holds out for the validation split (when
    ``TrainConfig.validation_cameras`` asks for none)."""
    max_frames: int | None = None
    """Validation frames per candidate (evenly spaced); None = all of the split."""
    cost: Literal["frame_ms", "model_ms"] = "frame_ms"
    """What "cheapest" measures: ``frame_ms`` = uv + cnn + sample + mlp per frame of one camera;
    ``model_ms`` = cnn + sample + mlp (leaves out the ray casting, which no capacity changes)."""
    ms_tie_rel: float = 0.05
    """Costs within this fraction of the lowest eligible cost count as a tie (fewest parameters wins)."""
    timing_repeats: int = 3
    """Timed evaluations per candidate: the validation pass, then ``timing_repeats - 1`` rounds over all
    candidates in turn (one frame each); each stage keeps its minimum, since other processes on a
    shared CPU only ever add time."""

    def __post_init__(self) -> None:
        if not self.tolerance_db >= 0:
            raise ValueError(f"AutoCapacityConfig: tolerance_db must be >= 0, got {self.tolerance_db}")
        if self.iters is not None and self.iters < 1:
            raise ValueError(f"AutoCapacityConfig: iters must be >= 1 or None, got {self.iters}")
        if self.split in TEST_SPLITS:
            raise ValueError(f"AutoCapacityConfig: split {self.split!r} is a test split; choosing a capacity on it "
                             "would report test numbers of a model selected on them. Use 'validation'")
        if self.split not in ("validation", "train"):
            raise ValueError(f"AutoCapacityConfig: split must be validation or train, got {self.split!r}")
        if self.validation_cameras < 1:
            raise ValueError(f"AutoCapacityConfig: validation_cameras must be >= 1, got {self.validation_cameras}")
        if self.cost not in ("frame_ms", "model_ms"):
            raise ValueError(f"AutoCapacityConfig: cost must be frame_ms or model_ms, got {self.cost!r}")
        if not self.ms_tie_rel >= 0:
            raise ValueError(f"AutoCapacityConfig: ms_tie_rel must be >= 0, got {self.ms_tie_rel}")
        if self.timing_repeats < 1:
            raise ValueError(f"AutoCapacityConfig: timing_repeats must be >= 1, got {self.timing_repeats}")
