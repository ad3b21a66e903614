"""Template specs recorded in a shard set's ``meta.h5`` rebuild every template kind through ``build_template``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from deliffas.data.shard_meta import read_meta, write_meta
from deliffas.data.shards import ShardSet
from deliffas.geometry.templates import (
    DDCTemplate,
    EmbeddedGraphTemplate,
    SMPLTemplate,
    Template,
    build_template,
    ddc_graph_spec,
    smpl_spec,
)
from deliffas.io.formats.dynacap.character import read_character
from tests.geometry.test_smpl import _synthetic_arrays


@pytest.fixture(scope="module")
def smpl_npz(tmp_path_factory):
    p = tmp_path_factory.mktemp("smpl_kind") / "body.npz"
    np.savez(p, **_synthetic_arrays())
    return p


def _rest_pose(t: Template) -> torch.Tensor:
    with torch.no_grad():
        return t.pose(torch.zeros(1, t.num_dofs, dtype=torch.float64))


def test_every_kind_rebuilds_from_a_shard_sets_recorded_spec(tmp_path, converted, smpl_npz):
    """convert records the spec in meta.h5; any kind's spec written there builds the same template."""
    meta = ShardSet(converted).meta
    spec = meta.template_spec()
    assert spec.kind == "ddc"
    character = read_character(spec.path("character"))
    from_shards = build_template(spec, dtype=torch.float64)
    assert isinstance(from_shards, DDCTemplate) and isinstance(from_shards, Template)
    assert torch.equal(_rest_pose(from_shards), _rest_pose(DDCTemplate(character, dtype=torch.float64)))
    assert np.array_equal(meta.faces, from_shards.faces.numpy())

    specs = {
        "ddc_graph": ddc_graph_spec(spec.path("character"), deformation="per_vertex"),
        "smpl": smpl_spec(smpl_npz, num_betas=4, atlas_res=256),
    }
    direct = {
        "ddc_graph": EmbeddedGraphTemplate(character, deformation="per_vertex", dtype=torch.float64),
        "smpl": SMPLTemplate(smpl_npz, num_betas=4, atlas_res=256, dtype=torch.float64),
    }
    for kind, s in specs.items():
        path = tmp_path / f"{kind}.h5"
        write_meta(path, dataclasses.replace(meta, attrs={**meta.attrs, "template_spec": s.to_json()}))
        recorded = read_meta(path).template_spec()
        assert recorded == s
        built = build_template(recorded, dtype=torch.float64)
        assert type(built) is type(direct[kind]) and built.num_dofs == direct[kind].num_dofs
        assert torch.allclose(_rest_pose(built), _rest_pose(direct[kind]), atol=1e-9)
