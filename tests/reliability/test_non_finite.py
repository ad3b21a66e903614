"""Nothing non-finite is written or rendered without an error: meshes (OBJ, PLY, ``.meshes``), shards, ``.avatar``
files and checkpoints refuse NaN/inf (and values beyond the stored dtype), and leave no file behind.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from deliffas.cli import main


def _only_error_line(capsys, match: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error:" in err[0] and match in err[0], err


def _tetra(scale: float = 1.0):
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64) * scale
    return verts, np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])


def test_ply_refuses_vertices_beyond_float32(tmp_path):
    from deliffas.io.mesh_files import write_mesh

    verts, faces = _tetra(1e307)  # finite in float64, inf in the PLY's float32
    with pytest.raises(ValueError, match=r"o.ply: vertices: 3 of 12 values are not finite as float32"):
        write_mesh(tmp_path / "o.ply", verts, faces)
    assert not any(tmp_path.iterdir())
    write_mesh(tmp_path / "o.ply", *_tetra(1e3))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_obj_and_meshes_refuse_non_finite(tmp_path, bad):
    from deliffas.io.formats.dynacap.meshes import MeshSequence, write_meshes
    from deliffas.io.mesh_files import write_mesh

    verts, faces = _tetra()
    verts[2, 1] = bad
    with pytest.raises(ValueError, match=r"o.obj: verts: 1 of 12 values are not finite"):
        write_mesh(tmp_path / "o.obj", verts, faces)
    with pytest.raises(ValueError, match=r"o.meshes: vertices: 1 of 12 values are not finite"):
        write_meshes(tmp_path / "o.meshes", MeshSequence(np.array([0]), verts[None]))
    assert not any(tmp_path.iterdir())


def test_pose_refuses_a_skeleton_that_poses_beyond_float32(sample_dir, tmp_path, capsys):
    """A skeleton with root offsets of 1e307 mm poses to finite float64 values that a PLY stores as inf."""
    char = tmp_path / "char"
    char.mkdir()
    for p in sample_dir.iterdir():
        if p.is_file():
            shutil.copyfile(p, char / p.name)
    lines = (char / "ddc.skeleton").read_text().splitlines()
    assert lines[2].split()[0] == "Root_tx"
    tok = lines[2].split()
    tok[4], tok[5] = "1e307", "1e307"  # the joint offset (x, y, z) of the root
    lines[2] = "  " + "  ".join(tok)
    (char / "ddc.skeleton").write_text("\n".join(lines) + "\n")
    out = tmp_path / "o.ply"
    assert main(["pose", str(char / "ddc.character"), str(sample_dir / "skeletoolToGTPose" / "poseAngles.motion"),
                 "--frame", "5", "--out", str(out)]) == 2
    _only_error_line(capsys, "not finite as float32")
    assert not out.exists()


def test_shard_writer_refuses_non_finite_geometry(tmp_path):
    from deliffas.data.shards import Codec, ShardGeometry, ShardWriter

    G, V, S = 2, 4, 4
    geo = ShardGeometry(np.array([0, 1]), np.zeros((G, 3)), np.zeros((G, V, 3)), np.full((G, V, 3), 1e39),
                        np.zeros((G, 3, S, S)), np.zeros((G, 3, S, S)))
    with pytest.raises(ValueError, match=r"training-00000.h5: geometry/outer_verts: 24 of 24 values are not finite"):
        ShardWriter(tmp_path / "shards" / "training-00000.h5", "training", [0, 1], [0], 8, 8, Codec.parse("raw"),
                    geo, 1, 0)
    assert not (tmp_path / "shards").exists() or not any((tmp_path / "shards").iterdir())


def _avatar_with_nan(path: Path, arrays: dict, record: dict) -> None:
    """What a buggy export writes: a NaN array with a valid sha256 (write_avatar_file itself refuses it)."""
    from safetensors.numpy import save

    from deliffas.io.avatar_file import AVATAR_FORMAT, AVATAR_VERSION, _array_sha256

    meta = {"format": AVATAR_FORMAT, "version": str(AVATAR_VERSION), "record": json.dumps(record),
            "sha256": json.dumps({k: _array_sha256(v) for k, v in arrays.items()})}
    path.write_bytes(save(arrays, metadata=meta))


def test_avatar_files_refuse_nan_arrays(tmp_path):
    from deliffas.io.avatar_file import AvatarFileError, read_avatar_file, write_avatar_file

    w = np.arange(6, dtype=np.float32).reshape(2, 3)
    w[1, 1] = np.nan
    with pytest.raises(ValueError, match=r"a.avatar: array 'model/w': 1 of 6 values are not finite"):
        write_avatar_file(tmp_path / "a.avatar", {"model/w": w}, {"kind": "avatar"})
    assert not any(tmp_path.iterdir())
    _avatar_with_nan(tmp_path / "b.avatar", {"model/w": w}, {"kind": "avatar"})
    with pytest.raises(AvatarFileError, match=r"b.avatar: array 'model/w' holds 1 NaN/inf of 6 values"):
        read_avatar_file(tmp_path / "b.avatar")


def test_checkpoint_with_nan_weights_is_refused(tmp_path):
    from deliffas.models.deliffas import DeliffasModel
    from deliffas.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
    from deliffas.models.zoo import get_config

    model = DeliffasModel(get_config("two_surface", "tiny"))
    with torch.no_grad():
        next(model.parameters())[0] = float("nan")
    save_checkpoint(tmp_path / "ckpt", model)
    with pytest.raises(CheckpointError, match=r"weights.safetensors: tensor '.*' holds \d+ NaN/inf values"):
        load_checkpoint(tmp_path / "ckpt")
