"""RenderPathConfig: how a command renders, the path and the uv source together (one frozen record).

Light (stdlib and :mod:`deliffas.options` only; ``deliffas.fast.shade.mlp_dtype`` resolves ``dtype``): ``eval``,
``render`` and ``view`` nest it in their configs (``render_path``), and ``deliffas.cli.from_config`` generates its
options (``--render-path``, ``--uv``, ``--render-dtype``, ``--fused-shade``, ``--pe-table``, ``--project-features``,
``--frames-in-flight``). Nothing here reads the environment.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Literal

from deliffas.options import check_fields, non_negative_int, opt

__all__ = ["RenderPathConfig", "PathName", "Dtype", "UVSource", "UV_SOURCES", "check_uv_source", "uv_field"]

PathName = Literal["fast", "plain"]
Dtype = Literal["auto", "float32", "bfloat16"]
UVSource = Literal["auto", "raster", "raycast", "torch"]
"""Where the uv maps come from (``deliffas.fast.uv_sources``: the three sources side by side, ``auto`` resolved)."""
UV_SOURCES = ("auto", "raster", "raycast", "torch")


def check_uv_source(requested: str) -> None:
    """ValueError naming the choices when ``requested`` is not one of ``UV_SOURCES``."""
    if requested not in UV_SOURCES:
        raise ValueError(f"uv: expected one of {', '.join(UV_SOURCES)}, got {requested!r}")


def uv_field() -> Any:
    """``uv: UVSource``: where the uv maps come from (``deliffas.fast.uv_sources.uv_source`` resolves ``auto``)."""
    return opt("auto", help="uv maps: raster (the C rasteriser, CPU), raycast (open3d, CPU), torch (the torch "
                            "rasteriser on --device); auto = raster where its C kernel builds (on CUDA, for "
                            "rendering: images of at most 2^19 pixels), else torch on CUDA and raycast on the CPU")


@dataclass(frozen=True)
class RenderPathConfig:
    """The render path (``fast``: ``deliffas.fast.frame``, the CPU's; ``plain``: ``model.shade`` in chunks, the
    reference numbers of ``deliffas eval``) and the uv source, which both paths take. ``fast`` on any other device
    than the CPU renders plain (``deliffas.fast.frame.path_for_device``). ``dtype``, ``fused``, ``pe_table``,
    ``project_features`` and ``in_flight`` are the fast path's and change nothing on the plain path.

    ``fused``: sampling, encodings and the whole MLP in one C pass (``FastShader.shade_fused``), its hidden layers
    in bf16 when ``dtype`` resolves to bf16 and the kernel has native bf16 dot products, else fp32. ``pe_table``:
    the fused fp32 pass takes the first layer's encoded part from per-coordinate tables (within 1e-4 of the exact
    pass). ``project_features``: the fused fp32 pass samples the feature layer's feature part from maps projected
    once per frame's features (within 1e-6); cheaper where a frame's features are shaded from several views (the
    viewer), dearer where each is shaded once (a video). ``in_flight``: frames ``render_stream`` renders at once.
    """

    path: PathName = opt("fast", help="fast = the CPU fast path (fused C shading, bf16 MLP where the CPU has "
                                      "native bf16, frames in flight); plain = the reference path (model.shade in "
                                      "chunks); on a GPU device both render plain", flag="--render-path")
    uv: UVSource = uv_field()
    dtype: Dtype = opt("auto", help="fast path: the MLP's dtype; auto = bfloat16 where the CPU has native bf16, "
                                    "else float32", flag="--render-dtype")
    fused: bool = opt(True, help="fast path: sampling, encodings and the MLP in one C pass (off: stage by stage)",
                      flag="--fused-shade")
    pe_table: bool = opt(True, help="fast path: the fused fp32 pass encodes from per-coordinate tables (off: the "
                                    "exact encoding)", flag="--pe-table")
    project_features: bool = opt(True, help="fast path: the fused fp32 pass samples maps projected once per "
                                            "frame's features (off: samples the features)",
                                 flag="--project-features")
    in_flight: int = opt(0, help="fast path: frames rendered at once; 0 = one per CPU core, at most 2",
                         flag="--frames-in-flight", parse=non_negative_int, metavar="N")

    def __post_init__(self) -> None:
        check_fields(self)  # the options' own checks: the Literal choices, --frames-in-flight's parse

    @property
    def fast(self) -> bool:
        """True on the fast path."""
        return self.path == "fast"

    def frames_in_flight(self) -> int:
        """The resolved number of frames in flight (>= 1); 1 on the plain path."""
        if not self.fast:
            return 1
        return self.in_flight or max(1, min(2, os.cpu_count() or 1))
