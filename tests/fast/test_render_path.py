"""``describe_render_path``: the line ``deliffas render -v`` / ``view -v`` print names the path taken and why."""

from __future__ import annotations

import dataclasses

from deliffas.fast.config import FastConfig
from deliffas.fast.frame import describe_render_path
from deliffas.models import DeliffasModel, get_config
from deliffas.models.zoo import REFLECTED


def test_default_model_takes_the_fast_path():
    model = DeliffasModel(get_config(REFLECTED, "small"))
    path = describe_render_path(model, FastConfig(), "cpu")
    line = path.line
    assert line.startswith("fast path, rasterised uvs") and "frame(s) in flight" in line
    assert ("fused C pass" in line and not path.fallback) or "the fused C kernel did not build" in line


def test_plain_path_says_why():
    model = DeliffasModel(get_config("two_surface", "tiny"))
    assert describe_render_path(model, None, "cpu").line.startswith("plain path (--plain)")
    assert "device meta" in describe_render_path(model, FastConfig(), "meta").line
    path = describe_render_path(model, dataclasses.replace(FastConfig(), fused=False, rasterize=False), "cpu")
    assert "ray-cast uvs" in path.line and "per-stage shading (fused=False)" in path.line and not path.fallback


def test_unsupported_variant_is_named():
    model = DeliffasModel(get_config("single_surface_two_unet", "tiny"))
    path = describe_render_path(model, FastConfig(), "cpu")
    assert "single_surface_two_unet is not one FastShader shades" in path.line and path.fallback
