"""Command-line options declared on config fields: :func:`opt` and the value parsers the fields name.

A config field that the command line sets is declared once, as ``name: type = opt(default, help=...)``;
``deliffas.cli.from_config`` turns it into the argparse option (spelling, type, choices, the default stated
in the help) and the parsed namespace back into the config. Stdlib only (a shared leaf): every layer's
config modules import it, and ``deliffas --help`` reads those modules without importing torch.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from dataclasses import MISSING
from pathlib import Path
from typing import Any, Callable

__all__ = ["CLI_KEY", "CliOption", "opt", "cli_option", "check_fields", "positive_int", "non_negative_int", "power_of_two",
           "positive_float", "non_negative_float", "open_unit_interval", "image_size", "int_list", "count_or_indices", "port",
           "device_name", "dask_target", "video_or_folder", "path_with_suffix"]

CLI_KEY = "deliffas.cli"
"""The key of a field's ``metadata`` holding its :class:`CliOption`."""


@dataclasses.dataclass(frozen=True)
class CliOption:
    """How a config field appears on the command line (see :func:`opt`)."""

    help: str
    flag: str | None = None
    parse: Callable[[str], Any] | None = None
    metavar: str | None = None
    default_text: str | None = None
    repeat: bool = False
    nargs: str | None = None
    choices: Callable[[], tuple[str, ...]] | None = None


def opt(default: Any = MISSING, *, help: str, flag: str | None = None, parse: Callable[[str], Any] | None = None,
        metavar: str | None = None, default_text: str | None = None, repeat: bool = False, nargs: str | None = None,
        choices: Callable[[], tuple[str, ...]] | None = None, default_factory: Any = MISSING) -> Any:
    """A dataclass field that the command line sets.

    Args:
        default: the field's default (no default: a required ``flag``, or a positional argument).
        help: the option's help text, without the default (the generator appends ``(default ...)``).
        flag: the option's spelling (``--iters``); None = ``--field-name``; ``""`` = a positional argument.
        parse: turns the text into the value (an argparse type, e.g. :func:`positive_int`); None = from the
            annotation (int, float, str, bool flags, ``Literal`` choices, ``X | None``).
        metavar: the value's name in the usage line.
        default_text: how the help states a default the value does not say itself (``"the run's"``).
        repeat: the option may be repeated; the values become a tuple.
        nargs: ``"?"`` for an optional positional argument.
        choices: the allowed values, asked for when the parser is built (names a registry holds, e.g. the camera
            formats; a ``Literal`` annotation states fixed ones).
        default_factory: as ``dataclasses.field``'s.
    """
    meta = {CLI_KEY: CliOption(help=help, flag=flag, parse=parse, metavar=metavar, default_text=default_text,
                               repeat=repeat, nargs=nargs, choices=choices)}
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def cli_option(f: dataclasses.Field) -> CliOption | None:
    """The field's :class:`CliOption`, or None when the command line does not set it."""
    return f.metadata.get(CLI_KEY)


def check_fields(config: Any) -> None:
    """Check every command-line field of ``config`` (a dataclass instance) as the command line checks its text,
    so a config built in Python is refused for what ``--option`` is: the field's ``parse`` run on the value, and a
    ``Literal`` annotation's choices. A config's ``__post_init__`` calls it; the check is declared once, on the
    field.

    None passes (an optional field left unset), and so does a tuple (its parser reads another spelling).

    Raises:
        ValueError: ``<field>: <what was expected>, got <value>``.
    """
    try:
        hints = typing.get_type_hints(type(config))
    except (NameError, TypeError):  # an annotation only a type checker resolves: the parsers still run
        hints = {}
    for f in dataclasses.fields(config):
        o = cli_option(f)
        value = getattr(config, f.name)
        if o is None or value is None or isinstance(value, tuple):
            continue
        choices = _literal_choices(hints.get(f.name))
        if choices and value not in choices:
            raise ValueError(f"{f.name}: expected one of {', '.join(map(str, choices))}, got {value!r}")
        if o.parse is not None and not isinstance(value, bool) and isinstance(value, (int, float, str, Path)):
            try:
                o.parse(str(value))
            except argparse.ArgumentTypeError as err:
                raise ValueError(f"{f.name}: {err}") from None
        elif o.parse is not None and isinstance(value, bool):
            kind = hints.get(f.name)
            raise ValueError(f"{f.name}: expected {getattr(kind, '__name__', kind) or 'a value'}, got {value!r}")


def _literal_choices(annotation: Any) -> tuple[Any, ...]:
    """The values of a ``Literal[...]`` annotation (also inside ``X | None``); () for any other."""
    if typing.get_origin(annotation) is typing.Literal:
        return typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return tuple(v for a in typing.get_args(annotation) for v in _literal_choices(a))
    return ()


def _int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: a whole number >= ``minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected a number >= {minimum}, got {value}")
        return value
    return parse


positive_int = _int_at_least(1)
non_negative_int = _int_at_least(0)


def positive_int_or_all(text: str) -> int | None:
    """A whole number >= 1, or ``all`` (None: no limit)."""
    if text.strip().lower() == "all":
        return None
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc}; or 'all'") from None


def power_of_two(text: str) -> int:
    """A power of two >= 16 (the U-Nets halve the atlas side down to a few texels)."""
    value = _int_at_least(16)(text)
    if value & (value - 1):
        lower = 1 << (value.bit_length() - 1)
        raise argparse.ArgumentTypeError(f"expected a power of two (the U-Nets halve it), got {value}; "
                                         f"try {lower} or {2 * lower}")
    return value


def _finite_float(text: str, positive: bool) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value > 0 if positive else value >= 0) or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a {'positive' if positive else 'non-negative'} finite number, "
                                         f"got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    return _finite_float(text, positive=True)


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    return _finite_float(text, positive=False)


def open_unit_interval(text: str) -> float:
    """A number strictly between 0 and 1."""
    value = _finite_float(text, positive=True)
    if not value < 1:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {text!r}")
    return value


def image_size(text: str) -> tuple[int, int]:
    """``WxH`` -> (W, H), both positive."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 256x256, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"image size must be positive, got {text!r}")
    return w, h


def int_list(text: str) -> tuple[int, ...]:
    """``a,b,...`` -> (a, b, ...)."""
    try:
        return tuple(int(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def count_or_indices(text: str) -> int | tuple[int, ...]:
    """``N`` (a count) or a list ``a,b,...`` (``3,`` names camera 3 alone)."""
    if "," in text or "[" in text:
        return int_list(text.strip("[]"))
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a count N or a list a,b,..., got {text!r}") from None


def port(text: str) -> int:
    """A TCP port, 1..65535."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 < value < 65536:
        raise argparse.ArgumentTypeError(f"port must be in 1..65535, got {value}")
    return value


def device_name(text: str) -> str:
    """``cpu``, ``cuda`` or ``cuda:N`` (whether this machine has it: ``engine.devices``)."""
    if text != "cpu" and text != "cuda" and not (text.startswith("cuda:") and text[5:].isdigit()):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}")
    return text


def dask_target(text: str) -> str:
    """A Dask scheduler address or ``local:N`` (``deliffas.parallel.dask_target``)."""
    from deliffas.parallel.dask_target import parse_dask_target  # local: a Ctrl-C at start-up meets main()

    try:
        parse_dask_target(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def video_or_folder(text: str) -> str:
    """A ``.mp4``/``.avi`` file, or a folder (no suffix) for PNG frames."""
    if Path(text).suffix and Path(text).suffix.lower() not in (".mp4", ".avi"):
        raise argparse.ArgumentTypeError(f"expected a .mp4 or .avi file or a folder without a suffix, got {text!r}")
    return text


def path_with_suffix(*suffixes: str) -> Callable[[str], Path]:
    """An argparse type: a path ending in one of ``suffixes`` (checked before any work starts)."""
    def parse(text: str) -> Path:
        p = Path(text)
        if p.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"expected a file ending in {' or '.join(suffixes)}, got {text!r}")
        return p
    return parse
