"""Loading a trained run: its model ready for inference and its recorded configuration."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from deliffas.models.deliffas import DeliffasModel
from deliffas.models.unet import optimize_for_inference
from deliffas.models.checkpoint import load_checkpoint

__all__ = ["load_run", "read_run_record"]


def load_run(run: str | Path, device: str | torch.device = "cpu") -> tuple[DeliffasModel, dict]:
    """The trained model (eval mode, U-Nets on their fused inference forward: ``optimize_for_inference``)
    and the run's recorded configuration."""
    run = Path(run)
    ckpt = load_checkpoint(run / "checkpoint", device)
    return optimize_for_inference(ckpt.model.eval()), read_run_record(run)


def read_run_record(run: str | Path) -> dict:
    """The run's recorded configuration (``train_config.json``; empty when the run has none)."""
    path = Path(run) / "train_config.json"
    return json.loads(path.read_text()) if path.is_file() else {}
