"""What ``deliffas eval`` is asked to do (:class:`EvalConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from deliffas.engine.config_fields import device_field
from deliffas.fast.config import RenderPathConfig
from deliffas.options import check_fields, opt, positive_int

__all__ = ["EvalConfig", "Split"]

Split = Literal["novel_view", "novel_pose", "validation", "train"]


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate."""

    run: str = opt(help="run directory written by `deliffas train`", flag="")
    split: Split = opt("novel_view", help="novel_view / novel_pose: test splits; validation: the run's held-out "
                                          "training cameras (--val-cameras at training); train: the fitted cameras")
    protocol: Literal["paper", "all"] | None = opt(None, help="frames: paper = every 10th, all = every frame",
                                                   default_text="the run's")
    shards: str | None = opt(None, help="shard directory", default_text="the run's")
    max_frames: int | None = opt(None, help="at most this many frames, evenly spaced", parse=positive_int,
                                 default_text="all")
    device: str = device_field()
    chunk_size: int = 262144
    """Rays shaded at once (bounds peak memory for large images)."""
    save_images: str | None = opt(None, help="folder for predicted images (white background), as "
                                             "<cam:03d>/<frame:06d>.png", default_text="none")
    vgg16_path: str | None = opt(None, help="ImageNet VGG-16 weights for LPIPS (.pth/.safetensors)",
                                 default_text="$DELIFFAS_VGG16_WEIGHTS / torch hub cache")
    lpips_path: str | None = opt(None, help="LPIPS v0.1 VGG linear layers (lpips' weights/v0.1/vgg.pth)",
                                 default_text="$DELIFFAS_LPIPS_WEIGHTS / the lpips package")
    inception_path: str | None = opt(None, help="pytorch-fid's pt_inception-2015-12-05-6726825d.pth for FID",
                                     default_text="$DELIFFAS_INCEPTION_WEIGHTS / torch hub cache")
    grid: str | None = opt(None, help="write a comparison grid (GT | prediction | error heat map, >= 256 px "
                                      "panels) of the first images", metavar="PNG", default_text="none")
    grid_images: int = 3
    """Rows of that grid (one image per frame, the first camera)."""
    render_path: RenderPathConfig = opt(RenderPathConfig(path="plain"),
                                        help="the plain path's numbers are the reference; --render-path fast "
                                             "measures what the CPU fast path of 'render' and 'view' changes")

    def __post_init__(self) -> None:
        check_fields(self)  # each option's own check, as on the command line
