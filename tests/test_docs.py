"""The documentation site: it builds with ``--strict``, strictness catches broken references, and the
API reference covers every module.

``make test`` also runs ``make docs`` (the same build into site/); here the build goes to a temporary
folder so that pytest alone (CI, a developer) checks it too, and the rendered pages are inspected.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MKDOCS = [sys.executable, "-m", "mkdocs", "build", "--strict"]  # not --quiet: it hides the warnings --strict counts

NO_TOOLS = "the docs tools are in the dev extra: pip install -e '.[dev]'"
pytest.importorskip("mkdocstrings_handlers.python", reason=NO_TOOLS)
pytest.importorskip("material", reason=NO_TOOLS)


def _load(name: str):
    """A helper module of the docs build (scripts/ is not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _build(config: Path, site: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run([*MKDOCS, "--config-file", str(config), "--site-dir", str(site)], cwd=config.parent,
                          env=env, capture_output=True, text=True, timeout=600)


def _modules() -> list[str]:
    """Every module of the package, as dotted names (``__main__`` is not API)."""
    names = []
    for path in sorted((REPO / "deliffas").rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        if parts[-1] == "__main__":
            continue
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("docs") / "site"
    built = _build(REPO / "mkdocs.yml", out)
    assert built.returncode == 0, f"mkdocs build --strict failed:\n{built.stdout[-3000:]}{built.stderr[-6000:]}"
    return out


def test_site_builds_strict_with_every_module(site):
    html = "\n".join(p.read_text(encoding="utf-8") for p in (site / "api").glob("*.html"))
    missing = [m for m in _modules() if f'id="{m}"' not in html]
    assert not missing, f"modules not in the API reference (add them to docs/api/*.md): {missing}"
    prose = re.sub(r"<pre.*?</pre>", "", html, flags=re.S)  # code (e.g. an attribute's value) is shown as written
    leftover = re.findall(r":(?:func|class|meth|mod|attr):`[^`<]+`", prose)
    assert not leftover, f"reST roles rendered literally: {leftover[:5]}"


def test_home_page_is_the_readme_with_its_picture(site):
    home = (site / "index.html").read_text(encoding="utf-8")
    readme_title = (REPO / "README.md").read_text(encoding="utf-8").splitlines()[0].lstrip("# ").strip()
    assert readme_title in home
    assert 'src="viewer.png"' in home and (site / "viewer.png").stat().st_size > 0
    assert 'href="api/geometry.html"' in home  # README's site/api/geometry.html, made site-relative
    for page in ("architecture", "conventions", "data", "geometry", "models", "shards", "performance",
                 "reliability", "scale", "results"):
        assert (site / f"{page}.html").is_file(), page


def _tiny_config() -> dict:
    """The site's mkdocs.yml for a throwaway project: same theme, checks, plugins and options; no hooks."""
    import yaml

    config = yaml.safe_load((REPO / "mkdocs.yml").read_text(encoding="utf-8"))
    for key in ("hooks", "nav", "site_description"):
        config.pop(key, None)
    python = next(p["mkdocstrings"] for p in config["plugins"] if isinstance(p, dict) and "mkdocstrings" in p)
    python = python["handlers"]["python"]
    python["paths"] = ["."]
    python["options"]["extensions"] = [  # griffe finds them from the working directory: make them absolute
        str(REPO / ext) if isinstance(ext, str) else {str(REPO / path): options for path, options in ext.items()}
        for ext in python["options"]["extensions"]]
    return {**config, "site_name": "tiny"}


GOOD_MODULE = '''"""Tiny: see :func:`present`."""


def present(x):
    """Present.

    Args:
        x: a parameter.
    """
'''


BROKEN = {
    "a docstring role naming nothing": ("module", ":func:`present`", ":func:`missing_function`", "missing_function"),
    "a page reference naming nothing": ("page", "", "See [x][deliffas.nonexistent].", "deliffas.nonexistent"),
    "a documented parameter that does not exist": ("module", "x: a parameter", "nope: a parameter", "'nope'"),
    "a page link to no page": ("page", "", "See [the guide](missing.md).", "missing.md"),
}
"""Each break: where (module or page), the good text it replaces (empty: appended), the bad text and what
the build's error names."""


def _tiny_project(root: Path, module: str, page: str) -> Path:
    (root / "tinypkg").mkdir(parents=True)
    (root / "tinypkg" / "__init__.py").write_text(module)
    (root / "docs").mkdir()
    (root / "docs" / "index.md").write_text(f"# tiny\n\n::: tinypkg\n\n{page}\n")
    config = root / "mkdocs.yml"
    config.write_text(json.dumps(_tiny_config()))  # JSON is YAML
    return config


def test_strict_build_fails_on_broken_references(tmp_path):
    """A throwaway project with the site's theme, plugins, options and griffe extensions builds; the same
    project with the four kinds of broken reference fails, naming each."""
    good = _build(_tiny_project(tmp_path / "good", GOOD_MODULE, ""), tmp_path / "good" / "site")
    assert good.returncode == 0, good.stderr[-3000:]
    module, page = GOOD_MODULE, ""
    for where, old, new, _ in BROKEN.values():
        if where == "module":
            assert old in module
            module = module.replace(old, new)
        else:
            page += f"\n{new}\n"
    broken = _build(_tiny_project(tmp_path / "broken", module, page), tmp_path / "broken" / "site")
    assert broken.returncode != 0, "the strict build passed with broken references"
    missed = [case for case, (*_, named) in BROKEN.items() if named not in broken.stderr]
    assert not missed, f"not reported: {missed}\n{broken.stderr[-3000:]}"


def test_roles_become_references():
    ext = _load("griffe_api_docs")
    import griffe

    pkg = griffe.visit("pkg", Path("pkg/__init__.py"), textwrap.dedent('''
        """Package."""
        from pkg.sub import helper as helper
    '''))
    sub = griffe.visit("sub", Path("pkg/sub.py"), '"""Sub."""\ndef helper(): ...\n', parent=pkg)
    pkg.set_member("sub", sub)
    convert = ext.convert_roles
    assert (convert(":func:`~pkg.sub.helper` and :class:`pkg.sub.C`", pkg)
            == "[`helper`][pkg.sub.helper] and [`pkg.sub.C`][pkg.sub.C]")
    assert convert(":func:`helper`", pkg) == "[`helper`][pkg.sub.helper]"  # resolved through the import
    assert convert(":mod:`.sub`", pkg) == "[`sub`][pkg.sub]"
    assert convert(":func:`_private` and :meth:`~pkg.C._hidden`", pkg) == "`_private` and `_hidden`"
    assert convert("plain ``code`` stays", pkg) == "plain ``code`` stays"


def test_readme_links_made_site_relative():
    home = _load("mkdocs_readme_home")
    md = ("![pic](docs/viewer.png) [guide](docs/geometry.md#atlas) [site](site/index.html) "
          "[api](site/api/index.html) [io](site/api/io.html) [`examples/`](examples/) "
          "[web](https://example.org/x) [top](#layout)")
    assert home.readme_as_home(md) == (
        "![pic](viewer.png) [guide](geometry.md#atlas) [site](index.md) [api](api/index.md) [io](api/io.md) "
        "`examples/` [web](https://example.org/x) [top](#layout)")
