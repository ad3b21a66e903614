"""Griffe extensions of the API reference (mkdocs.yml loads them): roles as cross-references, API dunders,
subpackages on pages of their own.

``SphinxRoles``: the docstrings are Google style with reST inline roles (``:func:`fit_smpl```,
``:class:`~a.b.C```). Markdown would print those literally; this turns each into an mkdocs-autorefs
link before the docstring is parsed, so ``mkdocs build --strict`` fails when one names nothing.

``~a.b.C`` shows ``C``, as in Sphinx. Names without the package (``fit_smpl``, ``Config.field``) are
resolved where the docstring is. Private names (a part starting with ``_``) are not in the
reference, so they stay plain code.

``HiddenDunders``: special methods that are machinery, not API (``__post_init__`` validation,
pickling, copying), are left out unless documented; protocol methods (``__len__``, ``__enter__``) stay.

``OptionHelp``: a config field declared with ``opt(..., help=...)`` has no field docstring (the help is its one
statement, tests/test_option_help.py); the reference shows the help as its docstring.

``SeparatePages``: the subpackages named in mkdocs.yml (``deliffas.geometry.templates``) are left out of
their parent's page, which lists every other module by itself; they are rendered where a page names
them (``::: deliffas.geometry.templates``).
"""

from __future__ import annotations

import ast
import re

import griffe

HIDDEN_DUNDERS = frozenset({"__post_init__", "__getstate__", "__setstate__", "__deepcopy__", "__copy__",
                            "__del__", "__reduce__", "__reduce_ex__"})
"""Special methods that are not part of a class's documented interface."""

ROLE = re.compile(r":(?:py:)?(?:mod|func|class|meth|attr|data|exc|obj|const):`(?P<tilde>~?)(?P<target>[^`]+)`")
"""A reST role naming a Python object: ``:func:`x```, ``:class:`~a.b.C```."""


def link(target: str, title: str, scope: griffe.Object) -> str:
    """The Markdown of a reference to ``target`` shown as ``title``, from a docstring of ``scope``.

    A name without the package (``fit_smpl``, ``Config.field``, ``subject`` from ``.subject``) is
    looked up where the docstring is, as Python would: its first part in ``scope``, then in its
    parents, through imports.
    """
    if any(part.startswith("_") and not part.startswith("__") for part in target.split(".")):
        return f"`{title}`"
    root = scope.package.name
    if target != root and not target.startswith(root + "."):
        first, _, rest = target.partition(".")
        try:
            first = scope.resolve(first)
        except griffe.NameResolutionError:
            pass  # left as written: the strict build reports it
        target = f"{first}.{rest}" if rest else first
    return f"[`{title}`][{target}]"


def convert_roles(text: str, scope: griffe.Object) -> str:
    """``text`` (a docstring of ``scope``) with every reST object role replaced by a reference."""
    def replace(match: re.Match) -> str:
        target = match["target"].strip().removesuffix("()").lstrip(".")
        title = target.rsplit(".", 1)[-1] if match["tilde"] else target
        return link(target, title, scope)
    return ROLE.sub(replace, text)


class SphinxRoles(griffe.Extension):
    """Rewrites the roles of every docstring once the object tree is complete."""

    def on_object(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = convert_roles(obj.docstring.value, obj)

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        self.on_object(obj=pkg)  # griffe fires on_object for the members of the package, not for itself


class HiddenDunders(griffe.Extension):
    """Removes the undocumented special methods of ``HIDDEN_DUNDERS`` from the classes of the package.

    Removed, not marked private: a class re-exported by its package (``deliffas.models.ModelConfig``)
    is rendered through an alias, whose members would not see such a mark.
    """

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        for cls in package_classes(pkg):
            for name in HIDDEN_DUNDERS & set(cls.members):
                if cls.members[name].docstring is None:  # a documented one says something about the API
                    cls.del_member(name)


def package_classes(pkg: "griffe.Module"):
    """Every class of ``pkg``, its submodules and nested classes (aliases, i.e. re-exports, left out)."""
    modules = [pkg]
    while modules:
        module = modules.pop()
        modules.extend(member for member in module.modules.values() if not member.is_alias)
        classes = [cls for cls in module.classes.values() if not cls.is_alias]
        while classes:
            cls = classes.pop()
            classes.extend(inner for inner in cls.classes.values() if not inner.is_alias)
            yield cls


def option_help(value: str) -> str | None:
    """The ``help=`` text of a field's value ``opt(..., help="...")`` (griffe's expression text); None when the value
    is no ``opt`` call or its help is not a literal (a part computed at import time is left out)."""
    try:
        call = ast.parse(value, mode="eval").body
    except SyntaxError:
        return None
    if not (isinstance(call, ast.Call) and getattr(call.func, "id", getattr(call.func, "attr", None)) == "opt"):
        return None
    node = next((k.value for k in call.keywords if k.arg == "help"), None)
    while isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):  # "literal: " + computed -> the literal
        node = node.left
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        text = node.value.strip().rstrip(":").strip()
        text = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")  # <cam:03d>: text, not a tag
        return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")
    return None


class OptionHelp(griffe.Extension):
    """Gives each undocumented ``opt`` field of a class its ``help=`` text as the docstring."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        for cls in package_classes(pkg):
            for attr in cls.attributes.values():
                text = None if attr.is_alias or attr.docstring is not None or attr.value is None \
                    else option_help(str(attr.value))
                if text:
                    attr.docstring = griffe.Docstring(text, parent=attr)


class SeparatePages(griffe.Extension):
    """Marks the listed modules private, so the ``public`` filter leaves them out of their parent's page."""

    def __init__(self, modules: list[str] = ()) -> None:
        super().__init__()
        self.modules = list(modules)

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        for path in self.modules:
            first, *parts = path.split(".")
            if first != pkg.name:
                continue
            module = pkg
            for part in parts:
                if part not in module.modules:
                    raise ValueError(f"mkdocs.yml, SeparatePages: {path} is not a module of {pkg.name} "
                                     f"(no {part!r} in {module.path})")
                module = module.modules[part]
            module.public = False
