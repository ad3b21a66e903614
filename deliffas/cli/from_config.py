"""argparse options generated from config dataclasses, and the configs built back from the parsed namespace.

Each field declared with :func:`deliffas.options.opt` becomes one option: its spelling (``flag``, else
``--field-name``), its type (``parse``, else the annotation: int, float, str, Path, ``Literal`` choices, ``X | None``,
bool as ``--flag`` / ``--no-flag``; ``choices=`` names values a registry holds), its help with the default appended,
and its ``dest`` = the field name.
A field whose type is itself a config dataclass (``EvalConfig.render_path``) is nested: its ``opt`` fields become
options of an argument group titled by the field, each stating the *outer* field's default value (so every
command states its own), bool ones as ``--flag`` / ``--no-flag``, with ``dest`` = ``field.subfield``; the
nested config is rebuilt from that default and the options given.
So an option is declared once, on its field, and a handler builds its config with :func:`config_from_args`.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import types
import typing
from pathlib import Path
from typing import Any, Iterable, Literal, Union

from deliffas.options import CliOption, cli_option

__all__ = ["DeprecatedAlias", "add_config_arguments", "config_from_args", "given_values", "option_names"]


def _cli_fields(cls: type) -> list[tuple[dataclasses.Field, CliOption]]:
    return [(f, o) for f in dataclasses.fields(cls) if (o := cli_option(f)) is not None]


def _annotation(cls: type, f: dataclasses.Field) -> Any:
    """The field's annotation as a type (postponed annotations evaluated in the config's module)."""
    if not isinstance(f.type, str):
        return f.type
    return eval(f.type, vars(sys.modules[cls.__module__]))  # noqa: S307 - the config module's own annotation


def _nested(cls: type, f: dataclasses.Field) -> type | None:
    """The config dataclass a nested field holds (``render_path: RenderPathConfig``), else None."""
    tp = _strip_none(_annotation(cls, f))
    return tp if isinstance(tp, type) and dataclasses.is_dataclass(tp) else None


def _strip_none(tp: Any) -> Any:
    """``X | None`` -> X (other unions unchanged)."""
    if typing.get_origin(tp) in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else tp
    return tp


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _shown(value: Any) -> str:
    if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value):
        return f"{value[0]}x{value[1]}"
    if isinstance(value, (tuple, list)):
        return ",".join(map(str, value)) or "none"
    return str(value)


def _help(f: dataclasses.Field, o: CliOption, default: Any, is_flag: bool) -> str:
    """The help text with its default: ``(default VALUE)`` or ``(default: DEFAULT_TEXT)``; none for on/off flags."""
    if is_flag or (default is dataclasses.MISSING and o.nargs is None):
        return o.help
    if o.default_text is not None:
        return f"{o.help} (default: {o.default_text})"
    if default is None or default == ():
        raise TypeError(f"{f.name}: the default None says nothing; give opt(..., default_text=...)")
    return f"{o.help} (default {_shown(default)})"


def _value_kwargs(cls: type, f: dataclasses.Field, o: CliOption) -> dict:
    """``type`` / ``choices`` of a field that takes a value."""
    if o.choices is not None:
        return {"choices": list(o.choices())} | ({"type": o.parse} if o.parse is not None else {})
    if o.parse is not None:
        return {"type": o.parse}
    tp = _strip_none(_annotation(cls, f))
    if o.repeat and typing.get_origin(tp) is tuple:
        tp = typing.get_args(tp)[0]
    if typing.get_origin(tp) is Literal:
        return {"choices": list(typing.get_args(tp))}
    if tp in (int, float, str, Path):
        return {"type": tp}
    raise TypeError(f"{cls.__name__}.{f.name}: no parser for {tp!r}; give opt(..., parse=...)")


def _add_field(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls: type, f: dataclasses.Field,
               o: CliOption, sparse: bool, nested_in: tuple[str, Any] | None = None) -> None:
    """``nested_in``: (the outer field's name, its default config) for a field of a nested config."""
    default = _default(f) if nested_in is None else getattr(nested_in[1], f.name)
    dest = f.name if nested_in is None else f"{nested_in[0]}.{f.name}"
    is_flag = _strip_none(_annotation(cls, f)) is bool and o.parse is None
    flag = o.flag if o.flag is not None else "--" + f.name.replace("_", "-")
    kwargs: dict[str, Any] = {"help": _help(f, o, default, is_flag)}
    if o.metavar is not None:
        kwargs["metavar"] = o.metavar
    if nested_in is not None:
        sparse = True  # the nested config's own default holds the values not given
        if is_flag:  # both spellings: the default differs between the commands nesting the config
            parser.add_argument(flag, dest=dest, action=argparse.BooleanOptionalAction, default=None,
                                help=f"{o.help} (default {'on' if default else 'off'})")
            return
    if is_flag:
        if default is True:
            flag = o.flag if o.flag is not None else "--no-" + f.name.replace("_", "-")
            kwargs.update(action="store_false")
        else:
            kwargs.update(action="store_true")
        kwargs["default"] = None if sparse else default
        parser.add_argument(flag, dest=dest, **kwargs)
        return
    kwargs.update(_value_kwargs(cls, f, o))
    if o.repeat:
        kwargs["action"] = "append"
    if not flag:  # positional: named by the field
        if o.nargs is not None:
            kwargs.update(nargs=o.nargs, default=None if sparse or default is dataclasses.MISSING else default)
        parser.add_argument(f.name, **kwargs)
        return
    if "metavar" not in kwargs and "choices" not in kwargs:  # named as spelt (--workers WORKERS), not by the field
        kwargs["metavar"] = flag.lstrip("-").replace("-", "_").upper()
    if default is dataclasses.MISSING:
        kwargs["required"] = True
    else:
        kwargs["default"] = None if sparse or o.repeat else default
    parser.add_argument(flag, dest=dest, **kwargs)


def _add_nested(parser: argparse.ArgumentParser, f: dataclasses.Field, o: CliOption, inner: type) -> None:
    """The options of a nested config field, in a group titled by the field (its ``help`` the description)."""
    base = _default(f)
    if not isinstance(base, inner):
        raise TypeError(f"{f.name}: a nested config field needs a {inner.__name__} default")
    group = parser.add_argument_group(f.name.replace("_", " "), o.help)
    for sf, so in _cli_fields(inner):
        _add_field(group, inner, sf, so, True, nested_in=(f.name, base))


def add_config_arguments(parser: argparse.ArgumentParser, cls: type, *, sparse: bool = False,
                         skip: Iterable[str] = ()) -> None:
    """One option per ``opt`` field of the dataclass ``cls`` (module docstring), in field order.

    Args:
        parser: the command's parser.
        cls: the config dataclass.
        sparse: every option defaults to None (a value the user did not give), for commands that merge the
            given options over another source (``train --config``, ``--resume``); the help still states the
            config's default.
        skip: field names another config of the same command already added.
    """
    for f, o in _cli_fields(cls):
        if f.name in skip:
            continue
        inner = _nested(cls, f)
        if inner is not None:
            _add_nested(parser, f, o, inner)
        else:
            _add_field(parser, cls, f, o, sparse)


def given_values(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """The values of ``cls``'s options in ``args`` that are not None (repeated options as tuples); a nested config
    as its default with the nested options given (absent when none is)."""
    values = {}
    for f, o in _cli_fields(cls):
        inner = _nested(cls, f)
        if inner is not None:
            changes = {sf.name: v for sf, _ in _cli_fields(inner) if (v := getattr(args, f"{f.name}.{sf.name}", None))
                       is not None}
            if changes:
                values[f.name] = dataclasses.replace(_default(f), **changes)
            continue
        value = getattr(args, f.name, None)
        if value is not None:
            values[f.name] = tuple(value) if o.repeat else value
    return values


def config_from_args(cls: type, args: argparse.Namespace, **extra: Any) -> Any:
    """``cls`` built from its options in ``args`` (absent ones keep the field's default) and ``extra``."""
    return cls(**{**given_values(cls, args), **extra})


def option_names(cls: type) -> dict[str, str]:
    """Field name -> how the command line spells it (``--iters``, or ``NAME`` for a positional argument); a nested
    config's fields as ``field.subfield`` (a bool one by its positive spelling)."""
    names = {}
    for f, o in _cli_fields(cls):
        inner = _nested(cls, f)
        if inner is not None:
            names.update({f"{f.name}.{sf.name}": so.flag or "--" + sf.name.replace("_", "-")
                          for sf, so in _cli_fields(inner)})
            continue
        flag = o.flag if o.flag is not None else "--" + f.name.replace("_", "-")
        if o.flag is None and _strip_none(_annotation(cls, f)) is bool and _default(f) is True:
            flag = "--no-" + f.name.replace("_", "-")
        names[f.name] = flag or f.name.upper()
    return names


class DeprecatedAlias(argparse.Action):
    """An old flag kept for one release: sets ``dest`` to ``const`` and adds a note naming ``replacement`` to
    ``args.deprecated``, which ``deliffas.cli.main`` logs as a warning once logging is set up."""

    def __init__(self, option_strings: list[str], dest: str, const: Any, replacement: str, **kwargs: Any):
        super().__init__(option_strings, dest, nargs=0, const=const, **kwargs)
        self.replacement = replacement

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        setattr(namespace, self.dest, self.const)
        note = f"{option_string} is deprecated and will be removed in the next release; use {self.replacement}"
        namespace.deprecated = [*(getattr(namespace, "deprecated", None) or []), note]
