"""Checkpoints: loading never executes code, and every damaged file gives a CheckpointError naming it.

- Pickle payloads (``__reduce__`` that creates a marker file) in ``weights.safetensors`` (with and
  without a matching SHA-256 in ``config.json``, raw pickle and torch.save zip), in
  ``optimizer.safetensors`` and in VGG-16 / LPIPS ``.pth`` weight files: a clear error, and the
  payload never runs (the control shows it would run under ``pickle.loads``). A source scan keeps
  ``pickle.load``/``torch.load`` without ``weights_only=True`` out of the package.
- Truncation sweep over every file of a saved training state (model weights, model config.json,
  optimizer.safetensors, train_state.json) and byte-flip sweep over the binary ones: each case
  raises ``CheckpointError`` whose message names the damaged file. Files of two different saves (a
  save interrupted by a kill) are detected too. ``deliffas train --resume`` on a truncated
  ``train_state.json`` exits 2 with the file named, no traceback.
"""

from __future__ import annotations

import builtins
import hashlib
import io
import json
import pickle
import random
import re
import shutil
import zipfile
from pathlib import Path

import pytest
import torch
from reliability_support import COUNTS

from deliffas.engine.checkpointing import (
    CHECKPOINT_DIR,
    OPTIMIZER_FILE,
    STATE_FILE,
    load_training_state,
    read_training_state,
    save_training_state,
)
from deliffas.models import DeliffasModel, get_config
from deliffas.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

PACKAGE = Path(__file__).resolve().parents[2] / "deliffas"


class _Payload:
    """Unpickling this creates ``marker`` (an observable side effect, no shell)."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (builtins.open, (self.marker, "w"))


def _pickle_bytes(marker: Path) -> bytes:
    return pickle.dumps({"weight": _Payload(marker)})


def _torch_zip_bytes(marker: Path) -> bytes:
    """A torch.save-style zip archive whose data.pkl carries the payload."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("archive/data.pkl", _pickle_bytes(marker))
        z.writestr("archive/version", "3\n")
    return buf.getvalue()


def _model() -> DeliffasModel:
    torch.manual_seed(0)
    return DeliffasModel(get_config("two_surface", "tiny"))


def _saved_run(run: Path) -> Path:
    model = _model()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    sum(p.sum() for p in model.parameters()).backward()
    opt.step()
    save_training_state(run, model, opt, {"iteration": 7, "perceptual_weight": None})
    return run


def _load(run: Path) -> dict:
    model = _model()
    return load_training_state(run, model, torch.optim.Adam(model.parameters(), lr=1e-3))


def test_control_payload_runs_under_plain_pickle(tmp_path):
    marker = tmp_path / "ran"
    pickle.loads(_pickle_bytes(marker))
    assert marker.exists()  # so the checks below would notice execution


@pytest.mark.parametrize("kind", ["pickle", "pickle+matching-sha", "torch-zip+matching-sha"])
def test_weights_pickle_payload_is_never_executed(tmp_path, kind):
    marker = tmp_path / "ran"
    ckpt = save_checkpoint(tmp_path / "ckpt", _model())
    blob = _torch_zip_bytes(marker) if kind.startswith("torch-zip") else _pickle_bytes(marker)
    (ckpt / "weights.safetensors").write_bytes(blob)
    if "matching-sha" in kind:  # the attacker also rewrites config.json to pass the checksum
        meta = json.loads((ckpt / "config.json").read_text())
        meta.update(weights_sha256=hashlib.sha256(blob).hexdigest(), weights_bytes=len(blob))
        (ckpt / "config.json").write_text(json.dumps(meta))
    # other weight-looking files in the folder are never looked at
    (ckpt / "model.pt").write_bytes(_torch_zip_bytes(marker))
    (ckpt / "weights.pkl").write_bytes(_pickle_bytes(marker))
    with pytest.raises(CheckpointError, match=r"weights\.safetensors"):
        load_checkpoint(ckpt)
    assert not marker.exists(), "loading a checkpoint executed pickled code"
    COUNTS["checkpoints: pickle payloads refused without running"] += 1


def test_optimizer_pickle_payload_is_never_executed(tmp_path):
    marker = tmp_path / "ran"
    run = _saved_run(tmp_path / "run")
    blob = _pickle_bytes(marker)
    (run / OPTIMIZER_FILE).write_bytes(blob)
    state = json.loads((run / STATE_FILE).read_text())
    state.update(optimizer_sha256=hashlib.sha256(blob).hexdigest(), optimizer_bytes=len(blob))
    (run / STATE_FILE).write_text(json.dumps(state))
    with pytest.raises(CheckpointError, match=r"optimizer\.safetensors"):
        _load(run)
    assert not marker.exists()
    COUNTS["checkpoints: pickle payloads refused without running"] += 1


@pytest.mark.parametrize("loader", ["vgg16", "lpips"])
def test_pth_weight_files_are_read_without_unpickling_code(tmp_path, loader):
    marker = tmp_path / "ran"
    path = tmp_path / "weights.pth"
    torch.save({"features.0.weight": _Payload(marker)}, path)  # a real torch.save archive with a payload
    if loader == "vgg16":
        from deliffas.models.vgg import load_vgg16_weights

        with pytest.raises(ValueError, match="weights.pth"):
            load_vgg16_weights("vgg16-imagenet", path=path)
    else:
        from deliffas.models.metrics import load_lpips_linear_weights

        with pytest.raises(ValueError, match="weights.pth"):
            load_lpips_linear_weights(path)
    assert not marker.exists()
    COUNTS["checkpoints: pickle payloads refused without running"] += 1


def test_package_never_unpickles():
    """Source scan: no pickle.load(s), no torch.load without weights_only=True, no numpy allow_pickle."""
    bad = []
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        for m in re.finditer(r"pickle\.loads?\(.*|torch\.load\(.*|allow_pickle\s*=\s*True", text):
            if m.group(0).startswith("torch.load(") and "weights_only=True" in m.group(0):
                continue
            bad.append(f"{path.relative_to(PACKAGE.parent)}: {m.group(0).strip()}")
    assert bad == []


def _cut_points(size: int, rng: random.Random, n: int) -> list[int]:
    fixed = {0, 1, 7, 8, 9, size // 2, size - 1}
    return sorted({c for c in fixed | {rng.randrange(0, size) for _ in range(n)} if 0 <= c < size})


def test_truncated_and_flipped_training_state_files_raise_naming_the_file(tmp_path):
    good = _saved_run(tmp_path / "good")
    assert _load(good)["iteration"] == 7
    files = {
        "weights.safetensors": good / CHECKPOINT_DIR / "weights.safetensors",
        "config.json": good / CHECKPOINT_DIR / "config.json",
        OPTIMIZER_FILE: good / OPTIMIZER_FILE,
        STATE_FILE: good / STATE_FILE,
    }
    rng = random.Random(7)
    cases = 0
    for name, path in files.items():
        blob = path.read_bytes()
        damaged = [("truncated at %d" % c, blob[:c]) for c in _cut_points(len(blob), rng, 10)
                   if blob[c:].strip()]  # dropping only the final newline damages nothing
        if name.endswith(".safetensors"):  # every byte is covered by a SHA-256
            for pos in [0, 8, len(blob) // 3, len(blob) - 1] + [rng.randrange(len(blob)) for _ in range(6)]:
                flipped = bytearray(blob)
                flipped[pos] ^= 1 << rng.randrange(8)
                damaged.append((f"bit flip at {pos}", bytes(flipped)))
        for what, data in damaged:
            run = tmp_path / "case"
            shutil.rmtree(run, ignore_errors=True)
            shutil.copytree(good, run)
            (run / path.relative_to(good)).write_bytes(data)
            with pytest.raises(CheckpointError) as info:
                _load(run)
            assert name in str(info.value), f"{name} {what}: message does not name the file: {info.value}"
            cases += 1
    COUNTS["checkpoints: truncated/flipped files refused"] += cases


def test_files_of_two_saves_are_detected(tmp_path):
    """A kill between the writes of one save leaves new weights/optimizer with the old train_state.json."""
    run = _saved_run(tmp_path / "run")
    old_state = (run / STATE_FILE).read_bytes()
    model = _model()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    load_training_state(run, model, opt)
    (sum(p.square().sum() for p in model.parameters())).backward()
    opt.step()
    save_training_state(run, model, opt, {"iteration": 8, "perceptual_weight": None})
    assert _load(run)["iteration"] == 8
    (run / STATE_FILE).write_bytes(old_state)  # as if killed before train_state.json was replaced
    with pytest.raises(CheckpointError, match="another save"):
        _load(run)
    load_checkpoint(run / CHECKPOINT_DIR)  # the model checkpoint alone stays loadable


def test_bad_state_json_shapes(tmp_path):
    run = _saved_run(tmp_path / "run")
    for text, match in [(b"\xff\xfe\x00", "UTF-8|utf-8"), (b"[1, 2]", "JSON object"), (b'{"iteration": "7"}', "iteration"),
                        (b'{"iteration": 7}', "optimizer_param_groups")]:
        (run / STATE_FILE).write_bytes(text)
        with pytest.raises(CheckpointError, match=match):
            _load(run)
    (run / STATE_FILE).unlink()
    with pytest.raises(CheckpointError, match="missing"):
        read_training_state(run)


def test_train_resume_cli_names_the_truncated_state_file(tmp_path, capsys):
    from deliffas.cli import main as cli_main

    run = _saved_run(tmp_path / "run")
    text = (run / STATE_FILE).read_bytes()
    (run / STATE_FILE).write_bytes(text[: len(text) // 3])
    rc = cli_main(["train", str(tmp_path / "no-shards"), "--model", "two_surface", "--preset", "tiny",
                   "--out", str(run), "--iters", "1", "--resume"])
    err = capsys.readouterr().err
    assert rc == 2 and "train_state.json" in err and "Traceback" not in err


def test_a_resumed_step_equals_the_uninterrupted_one_with_channels_last_atlases(tmp_path):
    """The texture atlases are channels-last parameters; their Adam moments, stored contiguous, come back in the
    parameter's layout, so that Adam's fused kernel (which pairs tensors by memory) takes the same step after a
    resume as without one."""
    from deliffas.engine.train import TrainConfig, make_optimizer

    def model_and_optimizer():
        torch.manual_seed(0)
        model = DeliffasModel(get_config("two_surface_reflect_texture", "tiny"))
        return model, make_optimizer(model, TrainConfig(shards="-", out="-"))

    def step(model, opt, k):
        opt.zero_grad()
        sum(((p * (k + 1)).sin() * p).sum() for p in model.parameters()).backward()
        opt.step()

    model, opt = model_and_optimizer()
    assert model.texture_inner.is_contiguous(memory_format=torch.channels_last)
    step(model, opt, 0)
    save_training_state(tmp_path / "run", model, opt, {"iteration": 1, "perceptual_weight": None})
    step(model, opt, 1)
    resumed, resumed_opt = model_and_optimizer()
    load_training_state(tmp_path / "run", resumed, resumed_opt)
    moment = resumed_opt.state[resumed.texture_inner]["exp_avg"]
    assert moment.stride() == resumed.texture_inner.stride()
    step(resumed, resumed_opt, 1)
    assert all(torch.equal(a, b) for a, b in zip(model.parameters(), resumed.parameters()))
