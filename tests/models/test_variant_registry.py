"""Tests of deliffas.models.variants (the registry) and deliffas.models.ray_query (RayQuery checks)."""

from __future__ import annotations

import pytest
import torch

from deliffas.models.deliffas import VARIANTS, DeliffasModel, ModelConfig
from deliffas.models.ray_query import RayQuery
from deliffas.models.variants import VariantSpec, get_variant, register_variant, unregister_variant, variant_names


def test_paper_variants_are_registered():
    assert set(VARIANTS) <= set(variant_names())
    assert get_variant("two_surface").outer_unet and get_variant("two_surface").inner_from_outer
    assert get_variant("single_surface_two_unet").inner_unets == 2
    assert get_variant("single_surface_viewdir").viewdir


def test_unknown_variant_lists_the_registered_ones():
    with pytest.raises(ValueError, match=r"unknown model variant 'nope'; registered: .*two_surface"):
        get_variant("nope")
    with pytest.raises(ValueError, match=r"ModelConfig: unknown model variant 'nope'; registered: single_surface"):
        ModelConfig(variant="nope")


def test_duplicate_registration_is_refused():
    with pytest.raises(ValueError, match="'two_surface' is already registered"):
        register_variant(VariantSpec("two_surface", outer_unet=True, encoded_uvs=("outer", "inner")))
    spec = register_variant(VariantSpec("test_dup"))
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_variant(VariantSpec("test_dup", viewdir=True))
    finally:
        unregister_variant("test_dup")
    with pytest.raises(ValueError, match="unknown model variant 'test_dup'"):
        unregister_variant(spec.name)


@pytest.mark.parametrize("kwargs, match", [
    (dict(inner_unets=0), "inner_unets"),
    (dict(encoded_uvs=(), viewdir=False), "encoded input"),
    (dict(encoded_uvs=("inner", "inner")), "distinct"),
    (dict(encoded_uvs=("middle",)), "distinct"),
    (dict(inner_from_outer=True), "inner_from_outer needs outer_unet"),
    (dict(inner_from_outer=True, outer_unet=True, inner_unets=2), "inner_from_outer needs"),
])
def test_spec_checks(kwargs, match, unchecked):
    with unchecked(), pytest.raises(ValueError, match=match):
        VariantSpec("bad", **kwargs)


def test_a_registered_spec_builds_a_model():
    spec = register_variant(VariantSpec("test_outer_viewdir", outer_unet=True, inner_unets=2, viewdir=True))
    try:
        cfg = ModelConfig(variant=spec.name, atlas_res=16, feature_channels=4, pe_freqs=2, viewdir_pe_freqs=1)
        model = DeliffasModel(cfg)
        assert model.spec is spec and len(model.inner_unets()) == 2 and model.unet_outer is not None
        assert model.mlp.feature_dim == 12 and model.mlp.in_dim == (2 + 8) + (3 + 6)
        normals = torch.randn(1, 9, 16, 16)
        f = model.encode(normals, normals)
        assert f.inner.shape[1] == 8 and f.outer.shape[1] == 4
        n = 7
        query = RayQuery(torch.zeros(n, dtype=torch.long), torch.rand(n, 2), torch.rand(n, 2),
                         torch.nn.functional.normalize(torch.randn(n, 3), dim=-1))
        assert model.shade(f, query).shape == (n, 3)
        with pytest.raises(ValueError, match="viewdir is required"):
            model.shade(f, RayQuery(query.batch_index, query.uv_inner, query.uv_outer))
        with pytest.raises(ValueError, match="no outer feature map"):
            model.shade(f, RayQuery(**{**query.__dict__, "inner_from_outer": torch.ones(n, dtype=torch.bool)}))
    finally:
        unregister_variant(spec.name)


def test_ray_query_shape_checks(unchecked):
    bi, uv = torch.zeros(4, dtype=torch.long), torch.rand(4, 2)
    q = RayQuery(bi, uv, uv, torch.rand(4, 3), torch.zeros(4, dtype=torch.bool))
    assert q.num_rays == 4 and q[1:3].num_rays == 2 and q[1:3].viewdir.shape == (2, 3)
    assert [c.num_rays for c in q.chunks(3)] == [3, 1]
    assert [c.num_rays for c in RayQuery(bi[:0], uv[:0]).chunks(3)] == [0]
    with unchecked(), pytest.raises(ValueError, match=r"uv_inner: expected shape \(N, 2\)"):
        RayQuery(bi, torch.rand(4, 3))
    with unchecked(), pytest.raises(ValueError, match="batch_index: dimension N should be 4"):
        RayQuery(bi[:3], uv)
    with unchecked(), pytest.raises(ValueError, match="uv_outer: dimension N should be 4"):
        RayQuery(bi, uv, uv_outer=torch.rand(5, 2))
    with unchecked(), pytest.raises(ValueError, match=r"viewdir: expected shape \(N, 3\)"):
        RayQuery(bi, uv, viewdir=torch.rand(4, 2))
    with unchecked(), pytest.raises(ValueError, match="inner_from_outer: expected dtype bool"):
        RayQuery(bi, uv, inner_from_outer=torch.zeros(4))
    with unchecked(), pytest.raises(ValueError, match="chunk_size"):
        next(q.chunks(0))
