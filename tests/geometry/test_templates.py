"""The template registry: kinds, recorded specs (JSON, source checks) and a kind added by one registration."""

from __future__ import annotations

import shutil

import pytest
import torch

from deliffas.geometry.templates import (
    Template,
    TemplateKind,
    TemplateSourceError,
    TemplateSpec,
    build_template,
    ddc_spec,
    make_spec,
    register_template_kind,
    template_kind,
    template_kinds,
)
from deliffas.io.formats.dynacap.character import read_character
from deliffas.io.obj import read_obj, write_obj, ObjData


def test_builtin_kinds_are_registered():
    assert {"ddc", "ddc_graph", "smpl"} <= set(template_kinds())


def test_unknown_kind_lists_the_registered_ones():
    with pytest.raises(ValueError, match=r"unknown template kind 'nope'.*ddc.*smpl"):
        build_template(TemplateSpec("nope"))


def test_a_kind_registers_once():
    with pytest.raises(ValueError, match="registered already"):
        register_template_kind(TemplateKind("ddc", lambda spec, dtype: None))


def test_kinds_own_their_motion_files_and_body_model_facts():
    assert [template_kind(k).motion_suffix for k in ("ddc", "ddc_graph", "smpl")] == [".motion", ".motion", ".npz"]
    assert [template_kind(k).smpl_params for k in ("ddc", "ddc_graph", "smpl")] == [False, False, True]


def test_spec_json_round_trip_and_errors(procedural_character_path):
    spec = ddc_spec(procedural_character_path, "lbs")
    assert TemplateSpec.from_json(spec.to_json()) == spec
    assert spec.option("skinning") == "lbs" and {"character", "skeleton", "mesh", "skin"} <= set(spec.files)
    assert all(len(h) == 64 for h in spec.sha256.values())
    with pytest.raises(ValueError, match="not JSON"):
        TemplateSpec.from_json("{kind")
    with pytest.raises(ValueError, match="unknown keys"):
        TemplateSpec.from_dict({"kind": "ddc", "file": {}})
    with pytest.raises(FileNotFoundError, match="'model' file does not exist"):
        make_spec("smpl", {"model": "/nonexistent/body.npz"})


def test_changed_or_missing_source_is_refused(tmp_path, procedural_character_path):
    src = procedural_character_path.parent
    dst = tmp_path / "character"
    shutil.copytree(src, dst)
    spec = ddc_spec(dst / procedural_character_path.name)
    build_template(spec)  # unchanged: builds
    skin = spec.path("skin")
    skin.write_text(skin.read_text() + "\n")
    with pytest.raises(TemplateSourceError, match=r"'skin' file changed"):
        build_template(spec)
    build_template(spec, verify=False)
    spec.path("skeleton").unlink()
    with pytest.raises(TemplateSourceError, match=r"'skeleton' file is gone"):
        build_template(spec)


class _RigidTemplate(torch.nn.Module):
    """A toy kind for the test: a mesh moved by a translation (3 parameters, mm)."""

    def __init__(self, obj: ObjData, dtype: torch.dtype):
        super().__init__()
        self.register_buffer("rest_verts", torch.tensor(obj.verts, dtype=dtype))
        self.register_buffer("faces", torch.as_tensor(obj.faces, dtype=torch.long))
        self.register_buffer("uvs", torch.tensor(obj.uvs, dtype=dtype))
        self.register_buffer("face_uvs", torch.as_tensor(obj.face_uvs, dtype=torch.long))

    num_verts = property(lambda self: int(self.rest_verts.shape[0]))
    num_dofs = property(lambda self: 3)

    def pose(self, dofs: torch.Tensor) -> torch.Tensor:
        return self.rest_verts[None] + dofs.to(self.rest_verts)[:, None, :]


def test_a_new_kind_is_one_registration(tmp_path, procedural_character_path):
    register_template_kind(TemplateKind("test_rigid", lambda spec, dtype: _RigidTemplate(read_obj(spec.path("mesh")), dtype)))
    mesh = read_character(procedural_character_path).mesh
    write_obj(tmp_path / "rigid.obj", mesh)
    t = build_template(make_spec("test_rigid", {"mesh": tmp_path / "rigid.obj"}))
    assert isinstance(t, Template)
    moved = t.pose(torch.tensor([[0.0, 10.0, 0.0]]))
    assert torch.allclose(moved[0, :, 1] - t.rest_verts[:, 1], torch.tensor(10.0))


def test_a_symlinked_character_is_built_from_the_files_its_spec_records(sample_dir, tmp_path):
    """A folder of symlinks to the sample with one link replaced by an edited copy: the spec hashes the files
    beside the link, and the build must read those same files (as ``read_character`` on that path does)."""
    import numpy as np

    from deliffas.data.posing import pose_frames
    from deliffas.geometry.templates.ddc import DDCTemplate

    links = tmp_path / "links"
    links.mkdir()
    for p in sample_dir.iterdir():
        (links / p.name).symlink_to(p)
    (links / "ddc.skeleton").unlink()
    lines = (sample_dir / "ddc.skeleton").read_text().splitlines()
    assert lines[2].split()[0] == "Root_tx"
    tok = lines[2].split()
    tok[4] = str(float(tok[4]) + 500.0)  # the root's offset moves by 500 mm in y
    lines[2] = "  " + "  ".join(tok)
    (links / "ddc.skeleton").write_text("\n".join(lines) + "\n")
    spec = ddc_spec(links / "ddc.character")
    assert spec.files["skeleton"] == str(links / "ddc.skeleton")
    motion = sample_dir / "skeletoolToGTPose" / "poseAngles.motion"
    posed, _ = pose_frames(spec, motion, [5])
    edited = DDCTemplate(read_character(links / "ddc.character"), dtype=torch.float64)
    original, _ = pose_frames(ddc_spec(sample_dir / "ddc.character"), motion, [5])
    from deliffas.io.formats.dynacap.character import read_motion

    dofs = read_motion(motion, edited.num_dofs)
    expected = edited.pose(torch.as_tensor(dofs.dofs[[dofs.row_of(5)]], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(posed, expected, atol=1e-6)
    assert np.abs(posed - original).max() > 100.0
