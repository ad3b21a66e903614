"""Loading a trained run: its model ready for inference and its recorded configuration."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from deliffas.models.deliffas import DeliffasModel
from deliffas.models.unet import optimize_for_inference
from deliffas.models.zoo import load_checkpoint

__all__ = ["load_run"]


def load_run(run: str | Path, device: str | torch.device = "cpu") -> tuple[DeliffasModel, dict]:
    """The trained model (eval mode, U-Nets on their fused inference forward: ``optimize_for_inference``)
    and the run's recorded configuration."""
    run = Path(run)
    ckpt = load_checkpoint(run / "checkpoint", device)
    record = json.loads((run / "train_config.json").read_text()) if (run / "train_config.json").is_file() else {}
    return optimize_for_inference(ckpt.model.eval()), record
