"""argparse options generated from config dataclasses, and the configs built back from the parsed namespace.

Each field declared with :func:`deliffas.options.opt` becomes one option: its spelling (``flag``, else
``--field-name``), its type (``parse``, else the annotation: int, float, str, Path, ``Literal`` choices, ``X | None``,
bool as ``--flag`` / ``--no-flag``; ``choices=`` names values a registry holds), its help with the default appended,
and its ``dest`` = the field name.
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

__all__ = ["add_config_arguments", "config_from_args", "given_values", "option_names"]


def _cli_fields(cls: type) -> list[tuple[dataclasses.Field, CliOption]]:
    return [(f, o) for f in dataclasses.fields(cls) if (o := cli_option(f)) is not None]


def _annotation(cls: type, f: dataclasses.Field) -> Any:
    """The field's annotation as a type (postponed annotations evaluated in the config's module)."""
    if not isinstance(f.type, str):
        return f.type
    return eval(f.type, vars(sys.modules[cls.__module__]))  # noqa: S307 - the config module's own annotation


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


def _add_field(parser: argparse.ArgumentParser, cls: type, f: dataclasses.Field, o: CliOption, sparse: bool) -> None:
    default = _default(f)
    is_flag = _strip_none(_annotation(cls, f)) is bool and o.parse is None
    flag = o.flag if o.flag is not None else "--" + f.name.replace("_", "-")
    kwargs: dict[str, Any] = {"help": _help(f, o, default, is_flag)}
    if o.metavar is not None:
        kwargs["metavar"] = o.metavar
    if is_flag:
        if default is True:
            flag = o.flag if o.flag is not None else "--no-" + f.name.replace("_", "-")
            kwargs.update(action="store_false")
        else:
            kwargs.update(action="store_true")
        kwargs["default"] = None if sparse else default
        parser.add_argument(flag, dest=f.name, **kwargs)
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
    parser.add_argument(flag, dest=f.name, **kwargs)


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
        if f.name not in skip:
            _add_field(parser, cls, f, o, sparse)


def given_values(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """The values of ``cls``'s options in ``args`` that are not None (repeated options as tuples)."""
    values = {}
    for f, o in _cli_fields(cls):
        value = getattr(args, f.name, None)
        if value is not None:
            values[f.name] = tuple(value) if o.repeat else value
    return values


def config_from_args(cls: type, args: argparse.Namespace, **extra: Any) -> Any:
    """``cls`` built from its options in ``args`` (absent ones keep the field's default) and ``extra``."""
    return cls(**{**given_values(cls, args), **extra})


def option_names(cls: type) -> dict[str, str]:
    """Field name -> how the command line spells it (``--iters``, or ``NAME`` for a positional argument)."""
    names = {}
    for f, o in _cli_fields(cls):
        flag = o.flag if o.flag is not None else "--" + f.name.replace("_", "-")
        if o.flag is None and _strip_none(_annotation(cls, f)) is bool and _default(f) is True:
            flag = "--no-" + f.name.replace("_", "-")
        names[f.name] = flag or f.name.upper()
    return names
