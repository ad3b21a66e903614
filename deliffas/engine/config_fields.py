"""Fields the engine's command configs share (device; test splits), declared once with their command-line help.

Light (stdlib and :mod:`deliffas.options` only): the CLI builds its parser from the configs that use them
without importing torch.
"""

from __future__ import annotations

from typing import Any

from deliffas.options import device_name, opt

__all__ = ["TEST_SPLITS", "device_field"]

TEST_SPLITS = ("novel_view", "novel_pose")
"""Splits that are test data: never used to choose a model, a capacity or a stopping point."""


def device_field() -> Any:
    """``device: str``: the torch device a command runs on (``engine.devices`` checks this machine has it)."""
    return opt("cpu", help="cpu | cuda | cuda:N", parse=device_name)
