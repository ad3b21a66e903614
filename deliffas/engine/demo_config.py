"""The sizes of ``deliffas demo`` (:class:`DemoConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.engine.run_sizes import RunSizes
from deliffas.engine.train_config import RAYS_PER_STEP
from deliffas.models.model_table import DEFAULT_MODEL
from deliffas.options import opt

__all__ = ["DemoConfig"]


@dataclass(frozen=True)
class DemoConfig:
    """Sizes of the demo run (defaults fit ~10 minutes on 2 CPU cores)."""

    out: str = opt("demo_out", help="output folder")
    quick: bool = opt(False, help="a much smaller run, for tests (seconds; its numbers are meaningless)")
    models: tuple[str, ...] = (DEFAULT_MODEL, "single_surface")
    sizes: RunSizes = RunSizes(frames=30, test_frames=10, cameras=10, iters=1200, supersample=2,
                               rays_per_step=RAYS_PER_STEP)
    """Ignored when ``quick`` (then ``RunSizes.quick()``). The capture is rendered with 2 x 2 rays per pixel: a
    camera integrates over its pixels, and at 128 px one ray per pixel aliases the skirt's plaid into lines that
    jump from view to view (the recipes render 3 x 3; 2 x 2 keeps the demo's synthesis under a minute)."""
    seed: int = 0
    jobs: int = 1
