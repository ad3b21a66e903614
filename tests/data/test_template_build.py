"""``deliffas template``: variants, outer shells and report on disk (on the procedural character)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deliffas.cli import main
from deliffas.io.formats.dynacap.character import read_character
from deliffas.io.obj import read_obj


@pytest.fixture(scope="module")
def built(tmp_path_factory, procedural_character_path):
    char_path = procedural_character_path
    out = tmp_path_factory.mktemp("template_build") / "templates"
    assert main(["template", str(char_path), "--out", str(out), "--smooth", "4",
                 "--coarse", "2500", "--atlas-res", "128"]) == 0
    return char_path, out


def test_variant_folders_and_outer_shells(built):
    char_path, out = built
    original = read_character(char_path)
    report = json.loads((out / "report.json").read_text())
    assert set(report["variants"]) == {"original", "smooth", "coarse"}
    assert report["offset_mm"] == 30.0 and report["safe"] is False
    for name in ("original", "smooth", "coarse"):
        c = read_character(out / name / f"{name}.character")
        outer = read_obj(out / name / "outer.obj")
        assert outer.num_verts == c.mesh.num_verts
        np.testing.assert_array_equal(outer.faces, c.mesh.faces)
        np.testing.assert_allclose(outer.uvs, c.mesh.uvs, atol=1e-6)
        np.testing.assert_array_equal(outer.face_uvs, c.mesh.face_uvs)
        d = np.linalg.norm(outer.verts - c.mesh.verts, axis=1)
        np.testing.assert_allclose(d, 30.0, atol=1e-4)
        from deliffas.geometry.mesh_ops import vertex_normals

        n = vertex_normals(c.mesh.verts, c.mesh.faces)
        assert (((outer.verts - c.mesh.verts) * n).sum(1) > 29.9).all(), "offset along the outward normal"
        v = report["variants"][name]
        assert v["num_verts"] == c.mesh.num_verts and v["num_faces"] == c.mesh.num_faces
        assert v["watertight"] is True and v["shell"]["watertight"] is True
        assert v["num_graph_nodes"] == c.graph.num_verts
        assert 0 < v["atlas"]["texel_coverage"] <= 1 and v["atlas"]["uvs_in_unit_square"]
        assert c.texture is not None and c.segmentation is not None and c.hand_segmentation is not None
        for f in (f"{name}.skeleton", f"{name}.skin", f"{name}.motion", f"{name}_graph.obj", "segmentation.txt"):
            assert (out / name / f).is_file(), (name, f)
    smooth = read_character(out / "smooth" / "smooth.character")
    np.testing.assert_array_equal(smooth.mesh.faces, original.mesh.faces)
    assert np.abs(smooth.mesh.verts - original.mesh.verts).max() > 0.1
    coarse = report["variants"]["coarse"]
    assert abs(coarse["num_faces"] - 2500) <= 250 and coarse["uv_source"] == "xatlas"


def test_safe_offsets_reduce_self_intersections(built, tmp_path):
    from deliffas.data.template_build import TemplateConfig, build_templates

    char_path, out = built
    unsafe = json.loads((out / "report.json").read_text())["variants"]["original"]["shell"]
    report = build_templates(TemplateConfig(char_path, tmp_path / "safe", offset_mm=30.0, safe=True, atlas_res=64))
    assert set(report["variants"]) == {"original"}
    safe = report["variants"]["original"]["shell"]
    assert safe["num_self_intersecting_faces"] <= unsafe["num_self_intersecting_faces"]
    assert safe["num_clamped"] > 0
    outer = read_obj(tmp_path / "safe" / "original" / "outer.obj")
    c = read_character(tmp_path / "safe" / "original" / "original.character")
    d = np.linalg.norm(outer.verts - c.mesh.verts, axis=1)
    assert d.max() <= 30.0 + 1e-4 and d.min() < 29.0


def test_bad_arguments(built, tmp_path):
    from deliffas.data.template_build import TemplateConfig, build_templates

    with pytest.raises(ValueError, match="offset_mm"):
        build_templates(TemplateConfig(built[0], tmp_path / "x", offset_mm=0.0))
    assert main(["template", str(tmp_path / "missing.character"), "--out", str(tmp_path / "y")]) == 2
