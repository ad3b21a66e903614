"""What ``deliffas render`` is asked to do (:class:`RenderConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.engine.config_fields import device_field
from deliffas.fast.config import RenderPathConfig
from deliffas.options import (check_fields, image_size, non_negative_int, opt, positive_float, positive_int,
                              video_or_folder)

__all__ = ["RenderConfig"]


@dataclass(frozen=True)
class RenderConfig:
    """A free-viewpoint render."""

    run: str = opt(help="run directory of 'deliffas train' or an .avatar file of 'deliffas export'", flag="")
    out: str = opt(help="video file (.mp4: H.264; .avi: Motion-JPEG) or a new folder for PNG frames",
                   parse=video_or_folder)
    orbit: bool = opt(False, help="camera orbits the avatar once over the video (default: a capture camera)")
    motion: str | None = opt(None, help=".motion (DDC template) or AMASS .npz (SMPL template)",
                             default_text="the capture's test motion")
    frames: int | None = opt(None, help="number of frames; more than the motion has needs --loop", parse=positive_int,
                             default_text="all of the motion, max 300")
    loop: bool = opt(False, help="play the motion again from its start to fill --frames")
    camera: int | None = opt(None, help="capture camera (calibration index) to render from; not with --orbit",
                             parse=non_negative_int, metavar="INDEX", default_text="the first test camera")
    overwrite: bool = opt(False, help="replace an existing --out video (a folder of PNGs must be new or empty)")
    size: tuple[int, int] | None = opt(None, help="WxH of the video", parse=image_size,
                                       default_text="the capture's image size")
    device: str = device_field()
    fps: float = opt(25.0, help="frames per second of the video", parse=positive_float)
    chunk_size: int = 262144
    render_path: RenderPathConfig = opt(RenderPathConfig(project_features=False),
                                        help="a video shades each frame's features once: projecting them costs "
                                             "more than it saves, so --project-features is off here")

    def __post_init__(self) -> None:
        check_fields(self)  # each option's own check, as on the command line
