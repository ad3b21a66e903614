"""FastShader equals DeliffasModel.shade: fp32 within round-off, bf16 within its precision; the fallback agrees."""

from __future__ import annotations

import platform

import pytest
import torch

import deliffas.fast.shade as fast_shade
from deliffas.models import DeliffasModel, get_config
from deliffas.models.deliffas import FrameFeatures
from deliffas.fast.shade import FastShader, supports
from deliffas.models.ray_query import RayQuery
from deliffas.native import LazyLibrary


def _case(variant: str, preset: str = "tiny", n: int = 3000, seed: int = 0):
    torch.manual_seed(seed)
    model = DeliffasModel(get_config(variant, preset)).eval()
    for p in model.mlp.parameters():  # non-zero biases, so a dropped bias would show
        p.data.add_(0.05 * torch.randn_like(p))
    cfg = model.config
    g = torch.Generator().manual_seed(seed)
    maps = [torch.rand(1, cfg.feature_channels, cfg.atlas_res, cfg.atlas_res, generator=g)
            .contiguous(memory_format=torch.channels_last) for _ in range(2)]
    feats = FrameFeatures(inner=maps[0], outer=maps[1] if model.spec.outer_unet else None)
    uv_in = torch.rand(n, 2, generator=g) * 1.1 - 0.05  # a few outside [0, 1]: border clamp
    uv_out = torch.rand(n, 2, generator=g)
    peel = (torch.rand(n, generator=g) < 0.2) if model.spec.inner_from_outer else None
    query = RayQuery(torch.zeros(n, dtype=torch.long), uv_in, uv_out if model.spec.uses_uv_outer else None, None, peel)
    return model, feats, query


@pytest.mark.parametrize("variant,preset", [("two_surface", "tiny"), ("two_surface", "small"),
                                            ("single_surface", "tiny")])
def test_fp32_equals_shade(variant, preset):
    model, feats, query = _case(variant, preset)
    with torch.no_grad():
        ref_enc, ref_feats = model.gather_inputs(feats, query)
        shader = FastShader(model)
        enc, fts = shader.inputs(feats, query)
        torch.testing.assert_close(enc, ref_enc, atol=2e-6, rtol=0)
        torch.testing.assert_close(fts, ref_feats, atol=2e-6, rtol=0)
        torch.testing.assert_close(shader.shade(feats, query), model.shade(feats, query), atol=2e-6, rtol=0)


def test_bf16_within_its_precision():
    model, feats, query = _case("two_surface", "small")
    with torch.no_grad():
        ref = model.shade(feats, query)
        got = FastShader(model, torch.bfloat16).shade(feats, query)
    assert got.dtype == torch.float32
    mse = float(((got - ref) ** 2).mean())
    assert float((got - ref).abs().max()) < 0.02 and -10 * torch.log10(torch.tensor(mse)) > 50


def test_weights_refresh_after_an_update():
    model, feats, query = _case("two_surface")
    shader = FastShader(model)
    with torch.no_grad():
        shader.shade(feats, query)
        model.mlp.output.bias.add_(0.5)
        torch.testing.assert_close(shader.shade(feats, query), model.shade(feats, query), atol=2e-6, rtol=0)


def test_fallback_without_the_kernel(monkeypatch):
    monkeypatch.setenv("DELIFFAS_NATIVE", "0")
    monkeypatch.setattr(fast_shade, "_KERNEL", LazyLibrary("ray_inputs", fast_shade._KERNEL.source, fallback="torch"))
    model, feats, query = _case("two_surface")
    with torch.no_grad():
        torch.testing.assert_close(FastShader(model).shade(feats, query), model.shade(feats, query), atol=2e-6, rtol=0)


def test_unsupported_variants_are_refused():
    model = DeliffasModel(get_config("single_surface_two_unet", "tiny"))
    assert not supports(model)
    with pytest.raises(ValueError, match="not supported"):
        FastShader(model)
    with pytest.raises(ValueError, match="dtype"):
        FastShader(DeliffasModel(get_config("two_surface", "tiny")), torch.float16)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_output_kernel_equals_torch_and_paints_rows(dtype):
    model, feats, query = _case("two_surface", "small")
    with torch.no_grad():
        fused, plain = FastShader(model, dtype), FastShader(model, dtype, use_kernel=False)
        enc, fts = plain.inputs(feats, query)
        tol = 2e-6 if dtype == torch.float32 else 0.02
        torch.testing.assert_close(fused.inputs(feats, query), (enc, fts), atol=tol, rtol=0)
        ref = plain.mlp(enc, fts)
        torch.testing.assert_close(fused.mlp(enc, fts), ref, atol=2e-6, rtol=0)
        rows = torch.randperm(2 * len(ref))[: len(ref)]
        canvas = torch.full((2 * len(ref), 3), 0.5)
        assert fused.mlp(enc, fts, out=canvas, rows=rows) is canvas
        torch.testing.assert_close(canvas[rows], ref, atol=2e-6, rtol=0)
        untouched = torch.ones(len(canvas), dtype=torch.bool)
        untouched[rows] = False
        assert bool((canvas[untouched] == 0.5).all())
        with pytest.raises(ValueError, match="canvas"):
            fused.mlp(enc, fts, out=canvas, rows=None)


@pytest.mark.parametrize("variant,preset", [("two_surface", "tiny"), ("two_surface", "realtime"),
                                            ("two_surface", "small"), ("single_surface", "tiny")])
def test_fused_pass_equals_shade(variant, preset):
    model, feats, query = _case(variant, preset, n=1000 + 7)  # a partial tile at the end
    with torch.no_grad():
        ref = model.shade(feats, query)
        shader = FastShader(model, torch.float32)
        assert shader.fused_available() == (fast_shade._FUSED.get() is not None)
        assert not shader.fused_bf16()  # fp32 shader: fp32 pass
        tol = 2e-6
        torch.testing.assert_close(shader.shade_fused(feats, query), ref, atol=tol, rtol=0)
        rows = torch.randperm(len(ref))
        canvas = torch.zeros(len(ref), 3)
        shader.shade_fused(feats, query, out=canvas, rows=rows)
        torch.testing.assert_close(canvas[rows], ref, atol=tol, rtol=0)
        off = FastShader(model, torch.float32, fused=False)  # the switch: the per-stage path
        assert not off.fused_available()
        torch.testing.assert_close(off.shade_fused(feats, query), ref, atol=2e-6, rtol=0)
        empty = RayQuery(query.batch_index[:0], query.uv_inner[:0],
                         query.uv_outer[:0] if query.uv_outer is not None else None, None,
                         query.inner_from_outer[:0] if query.inner_from_outer is not None else None)
        assert shader.shade_fused(feats, empty).shape == (0, 3)


@pytest.mark.parametrize("variant,preset", [("two_surface", "tiny"), ("two_surface", "realtime"),
                                            ("two_surface", "small"), ("single_surface", "tiny")])
def test_fused_pass_in_bf16_within_its_precision(variant, preset):
    """A bf16 shader's fused pass: bf16 hidden layers where the kernel has native bf16 dot products, else fp32;
    either way within bf16's precision of the fp32 reference (and without the kernel: the per-stage bf16 path)."""
    model, feats, query = _case(variant, preset, n=1000 + 7)
    with torch.no_grad():
        ref = model.shade(feats, query)
        shader = FastShader(model, torch.bfloat16)
        lib = fast_shade._FUSED.get()
        assert shader.fused_bf16() == (lib is not None and bool(lib.deliffas_fused_bf16()))
        got = shader.shade_fused(feats, query)
        mse = float(((got - ref) ** 2).mean())
        assert float((got - ref).abs().max()) < 0.02 and -10 * torch.log10(torch.tensor(mse)) > 50
        if not shader.fused_bf16() and shader.fused_available():
            torch.testing.assert_close(got, ref, atol=2e-6, rtol=0)
        rows = torch.randperm(len(ref))
        canvas = torch.zeros(len(ref), 3)
        shader.shade_fused(feats, query, out=canvas, rows=rows)
        torch.testing.assert_close(canvas[rows], got, atol=0, rtol=0)
        assert not FastShader(model, torch.bfloat16, fused=False).fused_bf16()  # the switches
        assert not FastShader(model, torch.bfloat16, use_kernel=False).fused_bf16()


def test_bf16_weight_pairs():
    w = torch.randn(6, 5)
    pairs = fast_shade._bf16_pairs(w).view(torch.bfloat16).reshape(3, 5, 2)  # low half first (little-endian)
    torch.testing.assert_close(pairs[:, :, 0], w[0::2].to(torch.bfloat16), atol=0, rtol=0)
    torch.testing.assert_close(pairs[:, :, 1], w[1::2].to(torch.bfloat16), atol=0, rtol=0)
    assert fast_shade._bf16_pairs(torch.zeros(0, 8)).shape == (0, 8)


def _fused_built_with(flag: str, monkeypatch) -> LazyLibrary:
    """The fused kernel built with one more compiler ``flag``, patched in as ``fast_shade._FUSED`` (skips when there
    is no compiler, or one that does not know the flag)."""
    lib = LazyLibrary(f"fused_shade{flag.replace('-', '_')}", fast_shade._FUSED.source,
                      (*fast_shade._FUSED.flags, flag), fallback="none")
    if lib.get() is None:
        pytest.skip(f"kernel not built with {flag}: {lib.load().reason}")
    monkeypatch.setattr(fast_shade, "_FUSED", lib)
    return lib


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="-mno-avx is an x86 flag")
def test_fused_pass_builds_and_agrees_without_avx(monkeypatch):
    """The kernel builds for x86 CPUs without AVX (SSE registers only; ``build_library`` also falls back to no
    ``-march`` at all, the same case) and agrees with ``shade``: the asm that keeps a tile in a register is left out
    where a tile is wider than the registers, which would not compile."""
    lib = LazyLibrary("fused_shade_no_avx", fast_shade._FUSED.source, (*fast_shade._FUSED.flags, "-mno-avx"),
                      fallback="none")
    built = lib.load()
    if built.lib is None and ("no C compiler" in built.reason or built.reason.startswith("disabled")):
        pytest.skip(built.reason)
    assert built.lib is not None, built.reason
    monkeypatch.setattr(fast_shade, "_FUSED", lib)
    model, feats, query = _case("two_surface", "realtime", n=300)
    with torch.no_grad():
        got = FastShader(model, pe_table=True, project_features=True).shade_fused(feats, query)
        torch.testing.assert_close(got, model.shade(feats, query), atol=2e-3, rtol=0)


def test_fused_pass_built_without_native_bf16_runs_fp32(monkeypatch):
    """The fallback of the bf16 hidden layers: a kernel built without AVX512-BF16 (here: -mno-avx512bf16) reports
    none, and a bf16 shader's fused pass then computes in fp32."""
    lib = _fused_built_with("-mno-avx512bf16", monkeypatch)
    assert not lib.get().deliffas_fused_bf16()
    model, feats, query = _case("two_surface", "realtime", n=500)
    with torch.no_grad():
        shader = FastShader(model, torch.bfloat16)
        assert shader.fused_available() and not shader.fused_bf16()
        torch.testing.assert_close(shader.shade_fused(feats, query), model.shade(feats, query), atol=2e-6, rtol=0)


@pytest.mark.parametrize("preset", ["realtime", "small"])
def test_fused_pass_in_eight_ray_tiles(monkeypatch, preset):
    """The tile width without AVX-512: a kernel built with -mno-avx512f shades 8 rays a tile (16 emulated in AVX2
    register pairs spilled and ran 5 x slower) and agrees with ``shade`` as the native build does, on partial
    tiles too (500 rays)."""
    lib = _fused_built_with("-mno-avx512f", monkeypatch)
    assert not lib.get().deliffas_fused_bf16()
    model, feats, query = _case("two_surface", preset, n=500)
    with torch.no_grad():
        shader = FastShader(model, torch.float32)
        assert shader.fused_available()
        torch.testing.assert_close(shader.shade_fused(feats, query), model.shade(feats, query), atol=2e-6, rtol=0)


def _table_case(variant: str, preset: str, n: int = 4003):
    """``_case`` with every uv in [0, 1] except the inner u of rays 2000-2099 (> 1: the table leaves their tiles to
    the encoder)."""
    model, feats, query = _case(variant, preset, n=n)
    uv_in = query.uv_inner.clamp(0, 1)
    outside = torch.zeros(n, dtype=torch.bool)
    outside[2000:2100] = True
    uv_in[outside, 0] = 1.001 + 0.2 * torch.rand(100)
    return model, feats, RayQuery(query.batch_index, uv_in, query.uv_outer, None, query.inner_from_outer), outside


def _table_agrees(model, feats, query, outside) -> None:
    with torch.no_grad():
        ref = FastShader(model).shade_fused(feats, query)
        got = FastShader(model, pe_table=True).shade_fused(feats, query)
    err = (got - ref).abs()
    mse = float((err**2).mean())
    assert float(err.max()) < 2e-3 and -10 * torch.log10(torch.tensor(mse)) > 70, (float(err.max()), mse)
    torch.testing.assert_close(got[outside], ref[outside], atol=2e-6, rtol=0)  # encoded exactly


@pytest.mark.parametrize("variant,preset", [("two_surface", "tiny"), ("two_surface", "realtime"),
                                            ("two_surface", "small"), ("single_surface", "tiny")])
def test_encoding_table_within_its_interpolation_error(variant, preset):
    """``pe_table``: the first layer's encoded part from per-coordinate tables agrees with the exact fused pass within
    the interpolation's error (which equals ``shade``); tiles with a uv outside [0, 1] are encoded exactly; the table
    is rebuilt when the weights change."""
    model, feats, query, outside = _table_case(variant, preset)
    shader = FastShader(model, pe_table=True)
    if not shader.fused_available():
        pytest.skip(f"the fused kernel is not built here: {fast_shade._FUSED.load().reason}")
    with torch.no_grad():
        torch.testing.assert_close(FastShader(model).shade_fused(feats, query), model.shade(feats, query), atol=2e-6,
                                   rtol=0)
    _table_agrees(model, feats, query, outside)
    table = shader.encoding_table()
    assert table is not None and table.shape[:3] == (2 * len(model.spec.encoded_uvs), fast_shade.TABLE_NODES + 1, 2)
    with torch.no_grad():
        model.mlp.hidden[0].weight.mul_(0.5)
    assert shader.encoding_table() is not table
    _table_agrees(model, feats, query, outside)


def test_encoding_table_in_eight_ray_tiles(monkeypatch):
    """The table in the 8-ray tiles of CPUs without AVX-512 (a kernel built with -mno-avx512f)."""
    _fused_built_with("-mno-avx512f", monkeypatch)
    _table_agrees(*_table_case("two_surface", "realtime"))


def test_bf16_fused_pass_ignores_the_table():
    """The table and the projected features serve the fp32 pass: with native bf16 a bf16 shader's fused pass is the
    same with and without them."""
    model, feats, query = _case("two_surface", "realtime", n=600)
    with torch.no_grad():
        a = FastShader(model, torch.bfloat16).shade_fused(feats, query)
        b = FastShader(model, torch.bfloat16, pe_table=True, project_features=True).shade_fused(feats, query)
    if FastShader(model, torch.bfloat16).fused_bf16():
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    else:  # no native bf16: the fused pass is fp32, and the table applies
        assert float((a - b).abs().max()) < 2e-3


def _feature_layer(model):
    return model.mlp.hidden[model.mlp.config.feature_layer + 1]


@pytest.mark.parametrize("pe_table", [False, True])
@pytest.mark.parametrize("variant,preset", [("two_surface", "tiny"), ("two_surface", "realtime"),
                                            ("two_surface", "small"), ("single_surface", "tiny")])
def test_projected_features_equal_sampled_features(variant, preset, pe_table):
    """``project_features``: the feature layer's part from projected maps equals sampling the features and multiplying
    (with and without the table; the tiny preset's features enter the tabled first layer), on peeled rays, a partial
    tile and uvs outside [0, 1]; the maps are cached, and rebuilt when the features or the weights change."""
    model, feats, query = _case(variant, preset, n=1000 + 7)
    shader = FastShader(model, pe_table=pe_table, project_features=True)
    if not shader.fused_available():
        pytest.skip(f"the fused kernel is not built here: {fast_shade._FUSED.load().reason}")
    sampled = FastShader(model, pe_table=pe_table)
    with torch.no_grad():
        torch.testing.assert_close(shader.shade_fused(feats, query), sampled.shade_fused(feats, query), atol=2e-6, rtol=0)
        maps = shader.projected_maps(feats)
        S, width = model.config.atlas_res, -(-_feature_layer(model).out_features // 8) * 8
        assert maps is not None and maps[1].shape == (S, S, width)
        assert (maps[0] is not None) == model.spec.outer_unet
        assert (maps[2] is not None) == (model.spec.outer_unet and model.spec.inner_from_outer)
        assert shader.projected_maps(feats) is maps
        feats.inner.mul_(0.5)  # in place: the same tensor, a new version
        assert shader.projected_maps(feats) is not maps
        torch.testing.assert_close(shader.shade_fused(feats, query), sampled.shade_fused(feats, query), atol=2e-6, rtol=0)
        maps = shader.projected_maps(feats)
        _feature_layer(model).weight.mul_(-1.5)
        assert shader.projected_maps(feats) is not maps
        torch.testing.assert_close(shader.shade_fused(feats, query), sampled.shade_fused(feats, query), atol=2e-6, rtol=0)
        other = FrameFeatures(inner=feats.inner.flip(2).contiguous(memory_format=torch.channels_last), outer=feats.outer)
        torch.testing.assert_close(shader.shade_fused(other, query), sampled.shade_fused(other, query), atol=2e-6, rtol=0)


def test_projected_features_beyond_their_budget_sample_the_features(monkeypatch):
    """Maps larger than ``PROJECTED_MAX_BYTES`` (the paper preset's) are not projected: the pass samples the features."""
    model, feats, query = _case("two_surface", "realtime", n=300)
    monkeypatch.setattr(fast_shade, "PROJECTED_MAX_BYTES", 1024)
    shader = FastShader(model, project_features=True)
    assert shader.projected_maps(feats) is None
    with torch.no_grad():
        torch.testing.assert_close(shader.shade_fused(feats, query), FastShader(model).shade_fused(feats, query),
                                   atol=0, rtol=0)


def test_projected_features_in_eight_ray_tiles(monkeypatch):
    """Projected features in the 8-ray tiles of CPUs without AVX-512 (a kernel built with -mno-avx512f)."""
    _fused_built_with("-mno-avx512f", monkeypatch)
    model, feats, query = _case("two_surface", "realtime", n=500)
    with torch.no_grad():
        torch.testing.assert_close(FastShader(model, pe_table=True, project_features=True).shade_fused(feats, query),
                                   FastShader(model, pe_table=True).shade_fused(feats, query), atol=2e-6, rtol=0)
