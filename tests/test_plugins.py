"""Entry-point discovery (``deliffas.plugins``): an installed package adds a template kind or a model variant
(the capture-format group is tested in tests/io/test_format_registry.py) with no deliffas file changed."""

from __future__ import annotations

import sys
import textwrap

import deliffas.plugins as plugins
from deliffas.geometry.templates import base as templates_base
from deliffas.geometry.templates import template_kind, template_kinds
from deliffas.models import variants
from deliffas.models.variants import get_variant, variant_names


def install(tmp_path, monkeypatch, module: str, group: str, source: str) -> None:
    """A fake distribution on sys.path: ``module``.py and a dist-info declaring it under ``group``."""
    (tmp_path / f"{module}.py").write_text(textwrap.dedent(source))
    dist = tmp_path / f"{module}-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module.replace('_', '-')}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{group}]\n{module} = {module}\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.setattr(plugins, "_LOADED", set())


def test_a_package_adds_a_template_kind(tmp_path, monkeypatch):
    template_kinds()
    monkeypatch.setattr(templates_base, "_KINDS", dict(templates_base._KINDS))
    install(tmp_path, monkeypatch, "toy_kinds", "deliffas.templates", """
        from deliffas.geometry.templates import TemplateKind, register_template_kind
        register_template_kind(TemplateKind("toy_rigid", lambda spec, dtype: None, motion_suffix=".toy"))
    """)
    assert "toy_rigid" in template_kinds() and template_kind("toy_rigid").motion_suffix == ".toy"


def test_a_package_adds_a_model_variant(tmp_path, monkeypatch):
    monkeypatch.setattr(variants, "_REGISTRY", dict(variants._REGISTRY))
    install(tmp_path, monkeypatch, "toy_variants", "deliffas.variants", """
        from deliffas.models.variants import VariantSpec, register_variant
        register_variant(VariantSpec("toy_three_unets", inner_unets=3, viewdir=True))
    """)
    assert get_variant("toy_three_unets").inner_unets == 3 and "toy_three_unets" in variant_names()


def test_a_group_is_loaded_once(tmp_path, monkeypatch):
    log = tmp_path / "loads.txt"
    install(tmp_path, monkeypatch, "toy_counter", "deliffas.toy", f"open({str(log)!r}, 'a').write('x')\n")
    plugins.load_plugins("deliffas.toy")
    plugins.load_plugins("deliffas.toy")
    assert log.read_text() == "x"
