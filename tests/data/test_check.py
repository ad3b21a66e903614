"""``deliffas check``: synthetic captures pass; each classic mistake fails and is named; the CLI and convert gate.

IoU numbers measured on these fixtures are in docs/data.md ("Checking a capture").
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from deliffas.cli import main
from deliffas.data.check import OPENGL_FROM_OPENCV, CheckConfig, check_subject
from deliffas.data.subjects import SubjectOptions, parse_subject
from deliffas.io.camera_conventions import rotvec_to_matrix
from deliffas.io.motion import Motion
from deliffas.io.formats.easymocap import read_easymocap_cameras, write_easymocap_cameras


@pytest.fixture(scope="session")
def smpl_parsed(smpl_subject):
    return parse_subject(smpl_subject)


def test_synthetic_subjects_pass(smpl_parsed, subject):
    for s in (smpl_parsed, parse_subject(subject)):
        r = check_subject(s)
        assert r.ok and not r.findings and np.all(r.camera_iou >= 0.95), r.camera_iou


def _cameras(subject, fn, which=None):
    return replace(subject, cameras=tuple(replace(c, world_to_cam=fn(c.world_to_cam.copy()))
                                          if which is None or i in which else c for i, c in enumerate(subject.cameras)))


def _transpose(E):
    E[:3, :3] = E[:3, :3].T
    return E


def _metres(E):
    E[:3, 3] /= 1000.0
    return E


def _pan(E):
    R = np.eye(4)
    R[:3, :3] = rotvec_to_matrix(np.array([0.0, 0.15, 0.0]))
    return R @ E


def _poses(subject, fn):
    return replace(subject, sequences={k: replace(s, poses=fn(s.poses)) for k, s in subject.sequences.items()})


def _smpl_mm(m):
    d = m.dofs.copy()
    d[:, :3] *= 1000.0
    return Motion(m.frames, d)


CORRUPTIONS = {
    "camera-to-world": (lambda s: _cameras(s, np.linalg.inv), "camera-to-world pose"),
    "transposed R": (lambda s: _cameras(s, _transpose), "transposed rotation"),
    "OpenGL axes": (lambda s: _cameras(s, lambda E: OPENGL_FROM_OPENCV @ E), "OpenGL camera axes"),
    "camera t in m": (lambda s: _cameras(s, _metres), "camera translation in metres read as mm"),
    "SMPL transl in mm": (lambda s: _poses(s, _smpl_mm), "SMPL translation in mm read as metres"),
    "frame offset": (lambda s: _poses(s, lambda m: Motion(m.frames, np.roll(m.dofs, -1, axis=0))), "frame offset"),
    "camera order": (lambda s: replace(s, cameras=tuple(s.cameras[i] for i in (1, 0, 3, 2))), "wrong camera order"),
    "one camera off": (lambda s: _cameras(s, _pan, which=(2,)), "a camera far below the others"),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_each_classic_mistake_is_named(name, smpl_parsed):
    corrupt, cause = CORRUPTIONS[name]
    r = check_subject(corrupt(smpl_parsed), CheckConfig(frames=4 if name == "frame offset" else 2))
    assert not r.ok and r.findings, (name, r.camera_iou)
    assert r.findings[0].cause.startswith(cause), (name, [f.cause for f in r.findings])
    assert r.findings[0].iou_after >= 0.95 and cause in r.reason
    if name == "one camera off":
        assert r.failed == (2,)


def _invert_cameras_on_disk(root):
    cams = read_easymocap_cameras(root / "intri.yml")
    inv = []
    for c in cams:
        R, T = c.R.T, -c.R.T @ c.T
        inv.append(type(c)(c.name, c.K, c.dist, R, T, c.width, c.height))
    write_easymocap_cameras(root, inv)


def test_cli_check_and_convert_gate(exported, smpl_model, tmp_path, capsys):
    root = tmp_path / "cap"
    shutil.copytree(exported("easymocap"), root)
    assert main(["check", str(root), "--template", str(smpl_model), "--out", str(tmp_path / "ok"), "--frames", "2"]) == 0
    summary = json.loads((tmp_path / "ok" / "summary.json").read_text())
    assert summary["ok"] and all(c["iou"] >= 0.95 for c in summary["cameras"])
    assert len(list((tmp_path / "ok" / "overlays").glob("*.png"))) == 4
    _invert_cameras_on_disk(root)
    capsys.readouterr()
    assert main(["check", str(root), "--format", "easymocap", "--template", str(smpl_model),
                 "--out", str(tmp_path / "bad"), "--frames", "2"]) == 1
    assert "camera-to-world" in (tmp_path / "bad" / "report.md").read_text()
    capsys.readouterr()
    assert main(["convert", str(root), str(tmp_path / "shards"), "--template", str(smpl_model), "--atlas-res", "16",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "camera-to-world" in err and "--no-check" in err and "Traceback" not in err and len(err.splitlines()) == 1
    assert main(["convert", str(root), str(tmp_path / "shards"), "--template", str(smpl_model), "--atlas-res", "16",
                 "--no-progress", "--no-check"]) == 0


@pytest.mark.parametrize("masks", ["missing", "empty", "full"])
def test_unusable_masks_are_named_and_no_calibration_fix_is_proposed(exported, smpl_model, tmp_path, masks):
    import cv2

    root = tmp_path / "cap"
    shutil.copytree(exported("easymocap"), root)
    for p in sorted((root / "mask").rglob("*.*")):
        if masks == "missing":
            p.unlink()
        else:
            m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(p), np.full_like(m, 0 if masks == "empty" else 255))
    result = check_subject(parse_subject(root, "easymocap", SubjectOptions(template=str(smpl_model))),
                           CheckConfig(frames=2))
    expected = "masks empty" if masks == "empty" else "masks missing or all foreground"
    assert not result.ok and len(result.findings) == 1 and result.findings[0].cause.startswith(expected)
    assert expected in result.reason and "1000" not in result.reason and "--no-check" not in result.reason
