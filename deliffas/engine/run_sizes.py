"""Sizes of a train-and-evaluate run on a synthetic capture, shared by the demo and the recipes."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["RunSizes"]


@dataclass(frozen=True)
class RunSizes:
    """How big a synthetic capture and its training run are.

    The defaults are a full recipe run (tens of minutes per model on 2 CPU cores); ``quick()`` is
    the size the tests use, where the numbers only show that the pipeline works.

    Attributes:
        frames: training frames of the synthetic capture.
        test_frames: novel-pose frames.
        cameras: cameras of the rig (some held out for novel-view evaluation).
        size: image side in pixels.
        atlas_res: side S of the atlas (normal maps and feature maps).
        iters: training iterations per model.
        cameras_per_frame: cameras per training sample.
        preset: zoo preset of the models ("paper", "small", "tiny").
        eval_frames: frames evaluated per split (None: all).
        rays_per_step: shaded rays per training iteration (``TrainConfig.rays_per_step``); None = every ray, as the
            recipes' documented runs trained.
        supersample: s, the synthetic capture's s x s rays per pixel (1: one ray through the pixel centre, which
            aliases texture finer than a pixel; a camera integrates over its pixels as s > 1 does).
    """

    frames: int = 40
    test_frames: int = 12
    cameras: int = 12
    size: int = 128
    atlas_res: int = 128
    iters: int = 1500
    cameras_per_frame: int = 3
    preset: str = "small"
    eval_frames: int | None = None
    supersample: int = 1
    rays_per_step: int | None = None

    @staticmethod
    def quick() -> "RunSizes":
        return RunSizes(frames=6, test_frames=2, cameras=4, size=48, atlas_res=32, iters=8, cameras_per_frame=2,
                        preset="tiny", eval_frames=2)
