"""The settings of ``deliffas view``, checked once when built."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from deliffas.engine.config_fields import device_field
from deliffas.fast.config import RenderPathConfig
from deliffas.options import opt, port, positive_int

__all__ = ["ViewConfig", "SubjectViewConfig", "is_exposed"]


def is_exposed(host: str) -> bool:
    """True when a server bound to ``host`` listens on more than the loopback interface."""
    return host not in ("127.0.0.1", "localhost", "::1")


def _check_port(value: int) -> None:
    if not 0 <= value <= 65535:
        raise ValueError(f"port must be in 0..65535, got {value}")


def _host_field() -> Any:
    return opt("127.0.0.1", help="interface to bind; 0.0.0.0 exposes the viewer and warns")


def _port_field() -> Any:
    return opt(8080, help="port", parse=port)


def _resolution_field() -> Any:
    return opt(512, help="longest side of the still image in pixels (halved while moving; SUBJECT: of the overlay at "
                         "a capture camera)", flag="--resolution", parse=positive_int)


@dataclass(frozen=True)
class ViewConfig:
    """What the free-viewpoint viewer shows and where it listens."""

    run: str = opt(help="run directory written by 'deliffas train', an .avatar file, or a capture folder (any "
                        "supported format)", flag="", metavar="RUN|SUBJECT")
    compare: str | None = opt(None, help="a second run on the same shards, side by side or toggled", default_text="none")
    motion: str | None = opt(None, help="driving motion: DynaCap .motion or SMPL .npz",
                             default_text="the capture's own frames")
    shards: str | None = opt(None, help="shard directory", default_text="the run's")
    host: str = _host_field()
    """Interface to bind; anything but localhost exposes the viewer (no authentication)."""
    port: int = _port_field()
    device: str = device_field()
    max_resolution: int = _resolution_field()
    """Longest side, in pixels, of the image rendered while the camera is still."""
    moving_scale: float = 0.5
    """Resolution factor while the camera moves (full resolution once it stops)."""
    still_after_s: float = 0.25
    """The camera counts as still this long after its last move."""
    jpeg_quality: int = 90
    """Quality of the frames sent while moving (still frames are sent as PNG)."""
    chunk_size: int = 262144
    """Rays shaded at once (bounds peak memory)."""
    max_frames: int = 300
    """At most this many frames of ``motion`` on the timeline."""
    render_path: RenderPathConfig = opt(RenderPathConfig(), help="the fast path on a CPU device, every switch on")

    def __post_init__(self) -> None:
        _check_port(self.port)
        if self.max_resolution < 16:
            raise ValueError(f"max_resolution must be >= 16 pixels, got {self.max_resolution}")
        if not 0 < self.moving_scale <= 1:
            raise ValueError(f"moving_scale must be in (0, 1], got {self.moving_scale}")
        if self.still_after_s < 0:
            raise ValueError(f"still_after_s must be >= 0, got {self.still_after_s}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {self.jpeg_quality}")
        if self.chunk_size < 1 or self.max_frames < 1:
            raise ValueError(f"chunk_size and max_frames must be >= 1, got {self.chunk_size}, {self.max_frames}")

    @property
    def exposed(self) -> bool:
        """True when the viewer listens on more than the loopback interface."""
        return is_exposed(self.host)


@dataclass(frozen=True)
class SubjectViewConfig:
    """What the capture viewer (``deliffas view SUBJECT``, a capture without a model) shows and where it listens."""

    subject: str
    """Capture folder (any format ``parse_subject`` reads)."""
    format: str = opt("auto", help="SUBJECT: capture format (auto = detected)")
    template: str | None = opt(None, help="SUBJECT: template, SMPL model .npz/.pkl (SMPL captures) or a DDC variant",
                               default_text="the capture's own")
    motions: tuple[str, ...] = ()
    """Pose parameters ``[SEQ=]FILE`` instead of the capture's own."""
    host: str = _host_field()
    """Interface to bind; anything but localhost exposes the viewer (no authentication)."""
    port: int = _port_field()
    max_resolution: int = _resolution_field()
    """Longest side, in pixels, of a capture camera's overlay (the silhouette and IoU are computed at this size)."""
    texture_resolution: int = 256
    """Longest side, in pixels, of the images on the camera frustums."""
    tolerance_px: int = 1
    """Pixels within this distance of the silhouette's edge are not scored (as ``deliffas check``)."""

    def __post_init__(self) -> None:
        _check_port(self.port)
        if self.max_resolution < 16 or self.texture_resolution < 8:
            raise ValueError(f"max_resolution must be >= 16 and texture_resolution >= 8 pixels, got "
                             f"{self.max_resolution}, {self.texture_resolution}")
        if self.tolerance_px < 0:
            raise ValueError(f"tolerance_px must be >= 0, got {self.tolerance_px}")

    @property
    def exposed(self) -> bool:
        """True when the viewer listens on more than the loopback interface."""
        return is_exposed(self.host)
