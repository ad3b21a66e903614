"""Fields the engine's command configs share (uv source, device; test splits), declared once with their command-line help.

Light (stdlib and :mod:`deliffas.options` only): the CLI builds its parser from the configs that use them
without importing torch.
"""

from __future__ import annotations

from typing import Any, Literal

from deliffas.options import device_name, opt

__all__ = ["UVSource", "UV_SOURCES", "TEST_SPLITS", "check_uv_source", "uv_field", "device_field"]

TEST_SPLITS = ("novel_view", "novel_pose")
"""Splits that are test data: never used to choose a model, a capacity or a stopping point."""

UVSource = Literal["auto", "raster", "raycast", "torch"]
"""Where the uv maps come from: ``raster`` = the C rasteriser (CPU, ``deliffas.fast.rasterize``), ``raycast`` =
the open3d ray caster (CPU), ``torch`` = the torch rasteriser on the model's device, ``auto`` = ``raster`` where
its C kernel builds, else ``torch`` on CUDA and ``raycast`` on the CPU."""
UV_SOURCES = ("auto", "raster", "raycast", "torch")


def check_uv_source(requested: str) -> None:
    """ValueError naming the choices when ``requested`` is not one of ``UV_SOURCES``."""
    if requested not in UV_SOURCES:
        raise ValueError(f"uv: expected one of {', '.join(UV_SOURCES)}, got {requested!r}")


def uv_field() -> Any:
    """``uv: UVSource``: where the uv maps come from (``engine.rays.uv_source`` resolves ``auto``)."""
    return opt("auto", help="uv maps: raster (the C rasteriser, CPU), raycast (open3d, CPU), torch (the torch "
                            "rasteriser on --device); auto = raster where its C kernel builds (on CUDA, for "
                            "rendering: images of at most 2^19 pixels), else torch on CUDA and raycast on the CPU")


def device_field() -> Any:
    """``device: str``: the torch device a command runs on (``engine.devices`` checks this machine has it)."""
    return opt("cpu", help="cpu | cuda | cuda:N", parse=device_name)
