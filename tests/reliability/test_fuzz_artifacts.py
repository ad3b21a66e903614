"""Property-based fuzzing of the engine's artifact readers: avatar files, model checkpoints and shard manifests.

Each case mutates a valid file (truncation, bit flips, spliced bytes, rewritten JSON) and the reader must
end in a record or its own ValueError naming the file (``AvatarFileError``, ``CheckpointError``, the
manifest's ``ValueError``) — never another exception type. ``make soak`` runs 10,000 cases per reader
(``reliability_support.FUZZ_EXAMPLES``).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from fuzz_mutations import bytes_cases
from reliability_support import COUNTS, FUZZ_EXAMPLES

from deliffas.data.shards import ShardSet
from deliffas.io.avatar_file import AvatarFileError, read_avatar_file, write_avatar_file
from deliffas.models.deliffas import DeliffasModel
from deliffas.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from deliffas.models.zoo import get_config

pytestmark = pytest.mark.timeout(300 if FUZZ_EXAMPLES <= 1000 else 3600)

SETTINGS = settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


_DIR = Path(tempfile.mkdtemp(prefix="deliffas-fuzz-artifacts-"))
write_avatar_file(_DIR / "a.avatar", {"w": np.arange(12, dtype=np.float32).reshape(3, 4),
                                      "template_file/mesh": np.frombuffer(b"v 0 0 0\n", np.uint8).copy()},
                  {"kind": "avatar", "model": {"atlas_res": 32}})
AVATAR = (_DIR / "a.avatar").read_bytes()
torch.manual_seed(0)
_tiny = get_config("two_surface", "tiny")
save_checkpoint(_DIR / "ckpt", DeliffasModel(_tiny), extra={"iteration": 1})
CONFIG_JSON = (_DIR / "ckpt" / "config.json").read_bytes()
WEIGHTS = (_DIR / "ckpt" / "weights.safetensors").read_bytes()
MANIFEST = json.dumps({"format": "deliffas-shards", "meta": {"name": "meta.h5"}, "shards": [], "planned": []},
                      indent=1).encode()


def test_avatar_file_fuzz(tmp_path):
    cases = 0

    @SETTINGS
    @given(data=bytes_cases(AVATAR))
    def run(data):
        nonlocal cases
        cases += 1
        p = tmp_path / "x.avatar"
        p.write_bytes(data)
        try:
            read_avatar_file(p)
        except AvatarFileError as err:
            assert str(p) in str(err)

    run()
    COUNTS["fuzz: avatar file cases"] += cases


@pytest.mark.parametrize("which", ["weights.safetensors", "config.json"])
def test_checkpoint_fuzz(tmp_path, which):
    cases = 0
    ckpt = tmp_path / "ckpt"
    shutil.copytree(_DIR / "ckpt", ckpt)
    valid = WEIGHTS if which == "weights.safetensors" else CONFIG_JSON

    @SETTINGS
    @given(data=bytes_cases(valid))
    def run(data):
        nonlocal cases
        cases += 1
        (ckpt / which).write_bytes(data)
        try:
            load_checkpoint(ckpt)
        except CheckpointError as err:
            assert which in str(err) or "config.json" in str(err)

    run()
    COUNTS[f"fuzz: checkpoint {which} cases"] += cases


def test_manifest_fuzz(tmp_path):
    cases = 0

    @SETTINGS
    @given(data=st.one_of(bytes_cases(MANIFEST), st.recursive(
        st.none() | st.booleans() | st.integers() | st.text(max_size=8),
        lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.sampled_from(
            ["format", "meta", "shards", "planned", "name", "sha256", "frames", "sequence", "bytes", "complete"]),
            inner, max_size=5), max_leaves=12).map(lambda v: json.dumps(v).encode())))
    def run(data):
        nonlocal cases
        cases += 1
        (tmp_path / "manifest.json").write_bytes(data)
        try:
            ShardSet(tmp_path)
        except ValueError as err:
            assert "manifest.json" in str(err)

    run()
    COUNTS["fuzz: shard manifest cases"] += cases
