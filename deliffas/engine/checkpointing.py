"""Training state on disk without pickle: model checkpoint (zoo format) + optimizer tensors + JSON."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from deliffas.models.deliffas import DeliffasModel
from deliffas.models.zoo import CheckpointError, load_checkpoint, save_checkpoint

__all__ = ["save_training_state", "load_training_state", "CHECKPOINT_DIR"]

CHECKPOINT_DIR = "checkpoint"
OPTIMIZER_FILE = "optimizer.safetensors"
STATE_FILE = "train_state.json"


def _atomic_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def save_training_state(run_dir: Path, model: DeliffasModel, optimizer: torch.optim.Optimizer,
                        state: dict[str, Any]) -> None:
    """Write the model checkpoint, the optimizer's tensors and the loop state (JSON), each atomically.

    ``train_state.json`` is written last, so a run killed mid-save resumes from the previous one.
    """
    from safetensors.torch import save as safetensors_save

    save_checkpoint(run_dir / CHECKPOINT_DIR, model, extra={"iteration": state["iteration"]})
    opt = optimizer.state_dict()
    tensors, scalars = {}, {}
    for pid, pstate in opt["state"].items():
        for key, value in pstate.items():
            if torch.is_tensor(value):
                tensors[f"{pid}.{key}"] = value.detach().cpu().contiguous()
            else:
                scalars[f"{pid}.{key}"] = value
    _atomic_bytes(run_dir / OPTIMIZER_FILE, safetensors_save(tensors))
    full = dict(state, optimizer_scalars=scalars, optimizer_param_groups=opt["param_groups"])
    _atomic_bytes(run_dir / STATE_FILE, (json.dumps(full, indent=2) + "\n").encode())


def load_training_state(run_dir: Path, model: DeliffasModel, optimizer: torch.optim.Optimizer | None,
                        device: str | torch.device = "cpu") -> dict[str, Any]:
    """Load what ``save_training_state`` wrote into ``model`` (and ``optimizer`` when given).

    Returns:
        The loop state (iteration, perceptual weight, ...).

    Raises:
        CheckpointError: missing or corrupted files (named in the message).
    """
    from safetensors.torch import load_file

    state_path = run_dir / STATE_FILE
    if not state_path.is_file():
        raise CheckpointError(f"{state_path}: missing (nothing to resume in {run_dir})")
    try:
        state = json.loads(state_path.read_text())
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{state_path}: corrupted JSON ({exc})") from exc
    ckpt = load_checkpoint(run_dir / CHECKPOINT_DIR, device)
    if ckpt.config != model.config:
        raise CheckpointError(f"{run_dir / CHECKPOINT_DIR}: its model config differs from the run's")
    model.load_state_dict(ckpt.model.state_dict())
    if optimizer is not None:
        try:
            tensors = load_file(str(run_dir / OPTIMIZER_FILE), device=str(device))
        except Exception as exc:  # safetensors raises its own error types for truncated files
            raise CheckpointError(f"{run_dir / OPTIMIZER_FILE}: unreadable ({exc})") from exc
        per_param: dict[int, dict] = {}
        for key, value in tensors.items():
            pid, name = key.split(".", 1)
            per_param.setdefault(int(pid), {})[name] = value
        for key, value in state.pop("optimizer_scalars", {}).items():
            pid, name = key.split(".", 1)
            per_param.setdefault(int(pid), {})[name] = value
        optimizer.load_state_dict({"state": per_param, "param_groups": state.pop("optimizer_param_groups")})
    return state
