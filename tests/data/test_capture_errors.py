"""Malformed capture files of each format: one ``error:`` line naming the file and the key, exit 2, no traceback."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest

from deliffas.cli import main
from deliffas.io.formats.zju_mocap import load_npy_dict


def _npy_drop(path, key):
    d = load_npy_dict(path)
    if "/" in key:
        outer, inner = key.split("/")
        del d[outer][inner]
    else:
        del d[key]
    np.save(path, np.array(d, dtype=object), allow_pickle=True)


def _text_replace(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def _json_drop(path, cam, key):
    data = json.loads(path.read_text())
    del data[cam][key]
    path.write_text(json.dumps(data))


def _npz_drop(path, key):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != key}
    np.savez(path, **arrays)


def _h5_drop(path, key):
    with h5py.File(path, "a") as h5:
        del h5[key]


CASES = {
    "zju annots": ("zju", lambda r: _npy_drop(r / "annots.npy", "cams/K"), "annots.npy: cams/K"),
    "zju params": ("zju", lambda r: _npy_drop(r / "params" / "1.npy", "Th"), "1.npy: Th"),
    "easymocap extri": ("easymocap", lambda r: _text_replace(r / "extri.yml", "T_2:", "X_2:"), "extri.yml: T_2"),
    "easymocap smpl": ("easymocap", lambda r: (r / "output" / "smpl" / "000001.json").write_text('[{"id": 0, "Rh": '),
                       "000001.json"),
    "thuman4 calibration": ("thuman4", lambda r: _json_drop(r / "calibration.json", "1", "R"), "calibration.json: 1.R"),
    "thuman4 smpl": ("thuman4", lambda r: _npz_drop(r / "smpl_params.npz", "transl"), "smpl_params.npz: transl"),
    "dna smplx": ("dna", lambda r: _h5_drop(r / "cap_dna.smc", "SMPLx/transl"), "cap_dna.smc: SMPLx/transl"),
    "dna calibration": ("dna", lambda r: _h5_drop(r / "cap_dna.smc", "Camera_Parameter/01/RT"),
                        "Camera_Parameter/01/RT"),
    "actorshq csv": ("actorshq", lambda r: _text_replace(r / "calibration.csv", ",fx,", ",focal,"),
                     "calibration.csv: header column fx"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_malformed_file_is_one_error_line(name, exported, smpl_model, tmp_path, capsys):
    fmt, corrupt, expected = CASES[name]
    root = tmp_path / exported(fmt).name
    shutil.copytree(exported(fmt), root)
    corrupt(root)
    capsys.readouterr()
    rc = main(["check", str(root), "--template", str(smpl_model), "--out", str(tmp_path / "report")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert expected in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
