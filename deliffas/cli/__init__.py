"""The ``deliffas`` command line: a thin layer of argument parsing over the Python API.

This module only parses (``deliffas --help`` imports no torch); the handlers that call the API are
:mod:`deliffas.cli.handlers`, imported when a command runs. Bad input ends in one ``error:`` line on
stderr and exit code 2 (``-v`` also logs the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from deliffas import __version__
from deliffas.cli.commands import COMMANDS, Command, Config
from deliffas.cli.from_config import add_config_arguments
from deliffas.cli.interrupted import report_interrupted
from deliffas.optional import interrupted_import

__all__ = ["main", "build_parser"]

log = logging.getLogger(__name__)


def _config_class(ref: str) -> type:
    """The config class named ``"module:Class"``; each row of the table names its configs this way."""
    module, _, name = ref.partition(":")
    # imported here, not at module level: the parser imports no torch at start-up (config modules are light), and a
    # Ctrl-C at start-up meets main(), which builds the parser inside its try
    return getattr(importlib.import_module(module), name)


def _add_command(sub, cmd: Command) -> None:
    """One row of the table: its parser, its options in the row's order, and its handler or subcommands."""
    p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.description)
    configs = [c if isinstance(c, Config) else Config(c) for c in cmd.configs]
    classes = tuple(_config_class(c.ref) for c in configs)
    at = len(configs) if cmd.extra_at is None else cmd.extra_at
    if cmd.positionals is not None:
        cmd.positionals(p, classes)
    for config, cls in zip(configs[:at], classes):
        add_config_arguments(p, cls, sparse=config.sparse, skip=config.skip)
    if cmd.extra is not None:
        cmd.extra(p, classes)
    for config, cls in zip(configs[at:], classes[at:]):
        add_config_arguments(p, cls, sparse=config.sparse, skip=config.skip)
    if cmd.subcommands:
        csub = p.add_subparsers(dest=f"{cmd.name.replace('-', '_')}_command", required=True, metavar=cmd.metavar)
        for subcommand in cmd.subcommands:
            _add_command(csub, subcommand)
    if cmd.handler is not None:
        p.set_defaults(handler=cmd.handler)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deliffas", description="deliffas: deformable light-field human avatars (DELIFFAS) - templates, captures, shards, training, evaluation and rendering. `deliffas COMMAND --help` explains each command.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    parser.add_argument("--version", action="version", version=f"deliffas {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for cmd in COMMANDS:
        _add_command(sub, cmd)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = None
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(name)s: %(message)s")
        for note in getattr(args, "deprecated", None) or ():  # DeprecatedAlias: an old flag's replacement
            log.warning("%s", note)
        from deliffas.cli import handlers  # local: keeps `deliffas --help` and parsing free of torch

        return int(getattr(handlers, f"cmd_{args.handler}")(args) or 0)
    except (ValueError, OSError) as err:  # bad input: every deliffas format/config error is a ValueError
        log.debug("traceback of the error below", exc_info=True)
        print(f"deliffas {args.command}: error: {_error_line(err)}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ImportError) as err:
        if not interrupted_import(err):  # an ImportError not caused by a Ctrl-C during the import
            raise
        return report_interrupted(args, argv)


_OS_HINTS = ((FileNotFoundError, "check the path"), (FileExistsError, "choose another path"),
             (PermissionError, "choose a path you may read or write"),
             (NotADirectoryError, "a file is where a folder is expected; check the path"))


def _error_line(err: Exception) -> str:
    """One line for a user: an OSError names its file, what failed and what to do (``[Errno 2] ...`` says none)."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror and str(err.filename) not in str(err.args[-1]):
        hint = next((h for kind, h in _OS_HINTS if isinstance(err, kind)), "")
        return f"{err.filename}: {err.strerror.lower()}" + (f"; {hint}" if hint else "")
    return str(err)
