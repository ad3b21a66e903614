"""``describe_render_path``: the line ``deliffas render -v`` / ``view -v`` print names the path taken and why."""

from __future__ import annotations

from deliffas.fast.config import RenderPathConfig
from deliffas.fast.frame import describe_render_path
from deliffas.models import DeliffasModel, get_config
from deliffas.models.zoo import REFLECTED


def test_default_model_takes_the_fast_path():
    model = DeliffasModel(get_config(REFLECTED, "small"))
    path = describe_render_path(model, RenderPathConfig(), "cpu")
    line = path.line
    assert line.startswith("fast path, rasterised uvs") and "frame(s) in flight" in line
    assert ("fused C pass" in line and not path.fallback) or "the fused C kernel did not build" in line


def test_plain_path_says_why():
    model = DeliffasModel(get_config("two_surface", "tiny"))
    line = describe_render_path(model, RenderPathConfig(path="plain"), "cpu").line
    assert line.startswith("plain path (--render-path plain): rasterised uvs")
    assert "device meta" in describe_render_path(model, RenderPathConfig(), "meta").line
    path = describe_render_path(model, RenderPathConfig(fused=False, uv="raycast"), "cpu")
    assert "ray-cast uvs" in path.line and "per-stage shading (--no-fused-shade)" in path.line and not path.fallback
    assert "uvs by the torch rasteriser" in describe_render_path(model, RenderPathConfig(uv="torch"), "cpu").line


def test_unsupported_variant_is_named():
    model = DeliffasModel(get_config("single_surface_two_unet", "tiny"))
    path = describe_render_path(model, RenderPathConfig(), "cpu")
    assert "single_surface_two_unet is not one FastShader shades" in path.line and path.fallback
