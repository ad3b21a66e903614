"""deliffas.environment: the only module that reads the environment, its table in the docs, and its readers."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from deliffas import environment
from deliffas.environment import VARIABLES, variables_markdown

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "deliffas"
DOC = REPO / "docs" / "architecture.md"
ALLOWED_WRITES = {
    "deliffas/cli/handlers.py": {"DASK_LOGGING__DISTRIBUTED"},
    "deliffas/data/ingest/detect.py": {"GLOG_minloglevel", "TF_CPP_MIN_LOG_LEVEL"},
}
"""``os.environ.setdefault(NAME, ...)`` calls that set a default for a third-party library, by file."""


def _is_os_environ(node: ast.AST) -> bool:
    return (isinstance(node, ast.Attribute) and node.attr in ("environ", "environb")
            and isinstance(node.value, ast.Name) and node.value.id == "os")


def environment_reads(source: str, allowed_writes: frozenset[str] = frozenset()) -> list[str]:
    """Every use of the environment in ``source``, as ``line: code``: ``os.environ`` / ``os.environb`` in any form
    (``.get``, ``[...]``, ``in``, passed on), ``os.getenv``, ``from os import environ/getenv``, except
    ``os.environ.setdefault(NAME, ...)`` with NAME in ``allowed_writes``."""
    tree = ast.parse(source)
    allowed: set[int] = set()
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "setdefault"
                and _is_os_environ(node.func.value) and node.args and isinstance(node.args[0], ast.Constant)
                and node.args[0].value in allowed_writes):
            allowed.add(id(node.func.value))
    found = []
    for node in ast.walk(tree):
        hit = (_is_os_environ(node) and id(node) not in allowed) or (
            isinstance(node, ast.Attribute) and node.attr in ("getenv", "getenvb")
            and isinstance(node.value, ast.Name) and node.value.id == "os") or (
            isinstance(node, ast.ImportFrom) and node.module == "os"
            and any(a.name in ("environ", "environb", "getenv", "getenvb") for a in node.names))
        if hit:
            found.append(f"{node.lineno}: {ast.get_source_segment(source, node)}")
    return found


def test_the_scan_finds_every_form_of_read():
    snippets = ['os.environ.get("X")', 'os.environ["X"]', '"X" in os.environ', 'os.getenv("X")', 'f(env=os.environ)',
                'from os import environ', 'from os import getenv as g', 'os.environ.setdefault("OTHER", "1")']
    for snippet in snippets:
        assert environment_reads(f"import os\n{snippet}\n", frozenset({"ALLOWED"})), snippet
    assert environment_reads('import os\nos.environ.setdefault("ALLOWED", "1")\n', frozenset({"ALLOWED"})) == []
    assert environment_reads("import os\nos.path.join('a', 'b')\n") == []


def test_only_the_environment_module_reads_the_environment():
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        if rel == "deliffas/environment.py":
            continue
        reads = environment_reads(path.read_text(encoding="utf-8"), frozenset(ALLOWED_WRITES.get(rel, ())))
        if reads:
            offenders[rel] = reads
    assert not offenders, f"read the environment through deliffas.environment instead: {offenders}"


def test_the_docs_table_is_the_variables():
    table = variables_markdown()
    assert table in DOC.read_text(encoding="utf-8"), "regenerate docs/architecture.md's table: variables_markdown()"
    names = [v.name for v in VARIABLES]
    assert len(names) == len(set(names))
    for v in VARIABLES:
        assert f"| `{v.name}` |" in table
        assert v.name and v.effect and v.default and v.reader.startswith("deliffas.")
        assert "|" not in v.effect + v.default and "\n" not in v.effect + v.default
        assert (PACKAGE.parent / (v.reader.replace(".", "/") + ".py")).is_file(), v.reader
    assert set(environment.WEIGHTS_VARIABLES) <= set(names)


def test_native_disabled_and_compiler():
    assert environment.native_disabled({}) is False
    assert environment.native_disabled({"DELIFFAS_NATIVE": "0"}) is True
    assert environment.native_disabled({"DELIFFAS_NATIVE": " 0\n"}) is True
    for value in ("1", "", "no", "00"):
        assert environment.native_disabled({"DELIFFAS_NATIVE": value}) is False
    assert environment.c_compiler({}) is None
    assert environment.c_compiler({"CC": "  "}) is None
    assert environment.c_compiler({"CC": "gcc"}) == ["gcc"]
    assert environment.c_compiler({"CC": "ccache 'my cc' -m64"}) == ["ccache", "my cc", "-m64"]


def test_native_constant_is_the_environment_one(monkeypatch):
    from deliffas import native

    assert native.NATIVE_ENV == environment.NATIVE_ENV == "DELIFFAS_NATIVE"
    monkeypatch.setenv("DELIFFAS_NATIVE", "0")
    assert environment.native_disabled() is True  # None = os.environ at call time
    lib = native.build_library("never", "never.c")
    assert lib.lib is None and "DELIFFAS_NATIVE=0" in lib.reason


def test_cache_root(monkeypatch):
    home = Path.home()
    assert environment.cache_root({}) == home / ".cache" / "deliffas"
    assert environment.cache_root({"DELIFFAS_CACHE": "", "XDG_CACHE_HOME": ""}) == home / ".cache" / "deliffas"
    assert environment.cache_root({"XDG_CACHE_HOME": "/x"}) == Path("/x/deliffas")
    assert environment.cache_root({"DELIFFAS_CACHE": "/c", "XDG_CACHE_HOME": "/x"}) == Path("/c")
    monkeypatch.setenv("DELIFFAS_CACHE", "/from/os")
    assert environment.cache_root() == Path("/from/os")


def test_weights_files():
    from deliffas.models import fid, lpips, vgg

    assert (vgg.ENV_VGG16_WEIGHTS, lpips.ENV_LPIPS_WEIGHTS, fid.ENV_INCEPTION_WEIGHTS) == environment.WEIGHTS_VARIABLES
    for name in environment.WEIGHTS_VARIABLES:
        assert environment.weights_file(name, {}) is None
        assert environment.weights_file(name, {name: ""}) is None
        assert environment.weights_file(name, {name: "/w/file.pth"}) == "/w/file.pth"
    with pytest.raises(ValueError, match="DELIFFAS_OTHER"):
        environment.weights_file("DELIFFAS_OTHER", {})


def test_onednn_isa_cap():
    assert environment.onednn_isa_cap({}) == "ALL"
    assert environment.onednn_isa_cap({"DNNL_MAX_CPU_ISA": "avx2"}) == "AVX2"
    both = {"ONEDNN_MAX_CPU_ISA": "avx512_core", "DNNL_MAX_CPU_ISA": "avx2"}
    assert environment.onednn_isa_cap(both) == "AVX512_CORE"
    assert environment.onednn_isa_cap({"ONEDNN_MAX_CPU_ISA": "", "DNNL_MAX_CPU_ISA": "avx2"}) == "AVX2"


def test_distributed():
    assert environment.distributed({}) == (1, 0)
    assert environment.distributed({"WORLD_SIZE": "4", "LOCAL_RANK": "3"}) == (4, 3)
    assert environment.world_size({"WORLD_SIZE": "2"}) == 2 and environment.local_rank({"LOCAL_RANK": "1"}) == 1
    with pytest.raises(ValueError):
        environment.world_size({"WORLD_SIZE": "two"})
    with pytest.raises(ValueError):
        environment.local_rank({"LOCAL_RANK": ""})


RENDER_PATH_VARIABLES = ("DELIFFAS_FAST_RENDER", "DELIFFAS_RENDER_DTYPE", "DELIFFAS_FUSED_SHADE", "DELIFFAS_PE_TABLE",
                         "DELIFFAS_PROJECT_FEATURES", "DELIFFAS_FRAMES_IN_FLIGHT")
"""Variables of earlier releases: the render path is ``RenderPathConfig``, set by options (``--render-path``...)."""


def test_no_variable_chooses_the_render_path():
    assert not set(RENDER_PATH_VARIABLES) & {v.name for v in VARIABLES}
    named = {path.relative_to(REPO).as_posix(): [n for n in RENDER_PATH_VARIABLES if n in path.read_text()]
             for path in PACKAGE.rglob("*.py")}
    assert not {k: v for k, v in named.items() if v}, "the render path is set by options, not the environment"
