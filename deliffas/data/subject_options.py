"""How a user asks for a capture to be read (:class:`SubjectOptions`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, Mapping

from deliffas.options import opt

if TYPE_CHECKING:
    from deliffas.geometry.templates import Skinning

__all__ = ["SubjectOptions"]


@dataclass(frozen=True)
class SubjectOptions:
    """Choices a user makes about how a capture is read (each format uses those it has)."""

    template: str | None = opt(None, help="template: SMPL model .npz/.pkl (SMPL captures; <stem>_uv.obj beside it is "
                                          "its uv layout), or a DDC variant folder (.character + optional outer.obj) "
                                          "or .character", default_text="the capture's own")
    skinning: Skinning = "dqs"
    """Skinning of a DDC template."""
    sequences: tuple[str, ...] | None = None
    """Sequences to read; None = the format's default ones that exist."""
    layout: Literal["auto", "images", "videos"] = "auto"
    """Frame layout (auto: images when present, else videos)."""
    masks: str | None = None
    """Mask folder inside each sequence folder replacing the images' alpha / fg videos."""
    motions: tuple[str, ...] = opt((), help="pose parameters instead of the capture's own: .motion (DDC) or AMASS "
                                            ".npz (SMPL) (SEQ default training; repeatable)", repeat=True,
                                   metavar="[SEQ=]FILE", default_text="the capture's own")
    meshes: tuple[str, ...] = ()
    """Tracked surfaces ``[SEQUENCE=]FILE.meshes`` (default sequence: training) instead of the posed template."""
    test_cameras: tuple[int, ...] | None = None
    """Held-out cameras; None = the capture's own split (or none)."""
    extra: Mapping[str, object] = field(default_factory=dict)
    """Format-specific options by name."""
