"""Training state on disk without pickle: model checkpoint (zoo format) + optimizer tensors + JSON.

``train_state.json`` is written last and records the SHA-256 and size of the optimizer file and the
model weights of the same save; loading checks them, so a truncated or corrupted file, or files of
two different saves (a save interrupted by a kill), raise ``CheckpointError`` naming the file
instead of resuming from a silent mixture.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch

from deliffas.io.infra.files import write_bytes_atomic
from deliffas.models.deliffas import DeliffasModel
from deliffas.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

__all__ = ["save_training_state", "load_training_state", "read_training_state", "CHECKPOINT_DIR"]

CHECKPOINT_DIR = "checkpoint"
OPTIMIZER_FILE = "optimizer.safetensors"
STATE_FILE = "train_state.json"


def save_training_state(run_dir: Path, model: DeliffasModel, optimizer: torch.optim.Optimizer,
                        state: dict[str, Any]) -> None:
    """Write the model checkpoint, the optimizer's tensors and the loop state (JSON), each atomically.

    ``train_state.json`` is written last with the checksums of the other two files. A run killed
    mid-save leaves files of two saves; ``load_training_state`` then raises ``CheckpointError``
    (the model checkpoint itself stays loadable on its own) rather than resuming from a mixture.
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
    blob = safetensors_save(tensors)
    write_bytes_atomic(run_dir / OPTIMIZER_FILE, blob)
    weights_sha = json.loads((run_dir / CHECKPOINT_DIR / "config.json").read_text())["weights_sha256"]
    full = dict(state, optimizer_scalars=scalars, optimizer_param_groups=opt["param_groups"],
                optimizer_sha256=hashlib.sha256(blob).hexdigest(), optimizer_bytes=len(blob),
                weights_sha256=weights_sha)
    write_bytes_atomic(run_dir / STATE_FILE, (json.dumps(full, indent=2) + "\n").encode())


def read_training_state(run_dir: Path) -> dict[str, Any]:
    """The loop state of ``run_dir/train_state.json`` (iteration, ...), checked.

    Raises:
        CheckpointError: the file is missing, not UTF-8 JSON, not an object, or lacks an integer
            ``iteration`` (named in the message).
    """
    path = Path(run_dir) / STATE_FILE
    if not path.is_file():
        raise CheckpointError(f"{path}: missing (nothing to resume in {run_dir})")
    try:
        state = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{path}: corrupted or truncated JSON ({exc})") from exc
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: expected a JSON object, got {type(state).__name__}")
    if not isinstance(state.get("iteration"), int) or isinstance(state.get("iteration"), bool):
        raise CheckpointError(f"{path}: expected an integer 'iteration', got {state.get('iteration')!r}")
    return state


def _check_blob(path: Path, blob: bytes, state: dict[str, Any], prefix: str) -> None:
    size, sha = state.get(f"{prefix}_bytes"), state.get(f"{prefix}_sha256")
    if size is not None and len(blob) != size:
        raise CheckpointError(f"{path}: truncated or from another save: {len(blob)} bytes, "
                              f"{STATE_FILE} records {size}")
    if sha is not None and hashlib.sha256(blob).hexdigest() != sha:
        raise CheckpointError(f"{path}: corrupted or from another save: SHA-256 differs from {STATE_FILE}")


def load_training_state(run_dir: Path, model: DeliffasModel, optimizer: torch.optim.Optimizer | None,
                        device: str | torch.device = "cpu") -> dict[str, Any]:
    """Load what ``save_training_state`` wrote into ``model`` (and ``optimizer`` when given).

    Returns:
        The loop state (iteration, perceptual weight, ...).

    Raises:
        CheckpointError: missing, truncated or corrupted files, or files of different saves (named
            in the message).
    """
    from safetensors.torch import load as safetensors_load

    run_dir = Path(run_dir)
    state_path = run_dir / STATE_FILE
    state = read_training_state(run_dir)
    ckpt = load_checkpoint(run_dir / CHECKPOINT_DIR, device)
    if ckpt.config != model.config:
        raise CheckpointError(f"{run_dir / CHECKPOINT_DIR}: its model config differs from the run's")
    weights_sha = state.get("weights_sha256")
    if weights_sha is not None:
        recorded = json.loads((run_dir / CHECKPOINT_DIR / "config.json").read_text())["weights_sha256"]
        if recorded != weights_sha:
            raise CheckpointError(f"{run_dir / CHECKPOINT_DIR}: written by another save than {state_path} "
                                  f"(iteration {state['iteration']}); was a save interrupted?")
    model.load_state_dict(ckpt.model.state_dict())
    if optimizer is not None:
        opt_path = run_dir / OPTIMIZER_FILE
        if not opt_path.is_file():
            raise CheckpointError(f"{opt_path}: missing")
        blob = opt_path.read_bytes()
        _check_blob(opt_path, blob, state, "optimizer")
        try:
            tensors = safetensors_load(blob)
        except Exception as exc:  # safetensors raises its own error types for truncated files
            raise CheckpointError(f"{opt_path}: unreadable ({exc})") from exc
        if "optimizer_param_groups" not in state:
            raise CheckpointError(f"{state_path}: missing key 'optimizer_param_groups'")
        params = [p for group in optimizer.param_groups for p in group["params"]]
        per_param: dict[int, dict] = {}
        try:
            for key, value in tensors.items():
                pid, name = key.split(".", 1)
                param = params[int(pid)]
                if value.dim() > 0:
                    if value.shape != param.shape:
                        raise ValueError(f"{key}: shape {tuple(value.shape)}, parameter {tuple(param.shape)}")
                    # in the parameter's memory layout (channels-last atlases): Adam's fused kernel pairs by memory
                    value = torch.empty_like(param, dtype=value.dtype).copy_(value)
                per_param.setdefault(int(pid), {})[name] = value.to(device)
            for key, value in state.pop("optimizer_scalars", {}).items():
                pid, name = key.split(".", 1)
                per_param.setdefault(int(pid), {})[name] = value
            optimizer.load_state_dict({"state": per_param, "param_groups": state.pop("optimizer_param_groups")})
        except (ValueError, IndexError, KeyError, TypeError) as exc:
            raise CheckpointError(f"{opt_path}: does not match the optimizer of this run ({exc})") from exc
    for key in ("optimizer_scalars", "optimizer_param_groups", "optimizer_sha256", "optimizer_bytes",
                "weights_sha256"):
        state.pop(key, None)
    return state
